"""Fusion: the composite 3D image after each epoch.

- ``keep_unchanged`` (also under the name ``keep_reference``): the known data stays, the changed elements of the new
  data come in, and the unchanged new elements are kept in the twin's history but hidden (the known data already
  images them);
- ``most_reliable``: as keep_unchanged, except where the new data images unchanged, measured (as-is) geometry inside
  its region of view with a smaller uncertainty (√det Σ, the volume of its error ellipsoid) than the known data:
  there the new data replaces the old (the paper's E2 replacing E1). Design (CAD) geometry stays the design unless
  ``replace_design``;
- ``replace_in_view``: the newest data always replaces what it images inside the region of view.

Replaced elements are hidden, not dropped; the numbers of the rule go into the epoch's report.

Change states are per epoch: elements carried over from an earlier epoch go back to "unchanged" unless this epoch
changes them; the first epoch is the baseline, so its elements are "unchanged" too. Removal needs the region of
view: with a region-of-view stage in the chain, a reference element in view that no recent data matches is
"removed" and leaves the composite (it stays in the history), and one outside the region of view is marked so and
kept as it was (never removed)."""

from __future__ import annotations

from gdt_pipeline import StageSpec, hookimpl

from ._compose import chain_check
from ._fitting import part_problems
from ._segments import PartParams, SegmentParams
from .keep_unchanged import KeepUnchangedParams, keep_unchanged
from .most_reliable import MostReliableParams, most_reliable
from .replace_in_view import ReplaceInViewParams, replace_in_view

__all__ = ["KeepUnchangedParams", "MostReliableParams", "PartParams", "ReplaceInViewParams", "SegmentParams",
           "gdt_stages"]


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in fusions."""
    common = {"family": "fusion", "version": "1.2.0", "requires": ("recent",),
              "optional": ("reference", "change", "rov"), "provides": ("composite",), "validate": part_problems}
    keep = "Known data stays; changed new elements come in; unchanged new ones are hidden."
    return [StageSpec(name="keep_unchanged", params=KeepUnchangedParams, run=keep_unchanged, description=keep,
                      check=chain_check("keep_unchanged", False), **common),
            StageSpec(name="keep_reference", params=KeepUnchangedParams, run=keep_unchanged,
                      description=keep + " (the same as keep_unchanged)", check=chain_check("keep_reference", False),
                      **common),
            StageSpec(name="most_reliable", params=MostReliableParams, run=most_reliable,
                      description="As keep_unchanged, but more precise new data replaces measured data in view.",
                      check=chain_check("most_reliable", True), **common),
            StageSpec(name="replace_in_view", params=ReplaceInViewParams, run=replace_in_view,
                      description="The newest data replaces what it images inside the region of view.",
                      check=chain_check("replace_in_view", True), **common)]
