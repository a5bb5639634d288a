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

from . import keep_unchanged, most_reliable, replace_in_view
from ._segments import PartParams, SegmentParams
from .keep_unchanged import KeepUnchangedParams
from .most_reliable import MostReliableParams
from .replace_in_view import ReplaceInViewParams

__all__ = ["KeepUnchangedParams", "MostReliableParams", "PartParams", "ReplaceInViewParams", "SegmentParams",
           "gdt_stages"]


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in fusions."""
    return [keep_unchanged.KEEP_UNCHANGED, keep_unchanged.KEEP_REFERENCE, most_reliable.SPEC, replace_in_view.SPEC]
