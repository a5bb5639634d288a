"""The slots of an epoch's context, written once: what each holds, and the check the runner applies to a stage's
output for it. Slots a third party invents are passed through unchecked."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .types import Change, Composite, Correspondences, Dataset, EpochInfo, RegionOfView, Registration, Scores

# Slots the engine fills before the first stage runs (``reference`` too, from the second epoch on).
ENGINE_SLOTS = frozenset({"recent", "epoch"})
# The slot every epoch's chain must end by providing: the twin's new state.
FINAL_SLOT = "composite"


def _list_of(cls: type) -> Callable[[Any], bool]:
    return lambda v: isinstance(v, list | tuple) and all(isinstance(x, cls) for x in v)


@dataclass(frozen=True)
class Slot:
    """One named slot: what it holds and how to recognise a valid value."""

    name: str
    holds: str
    check: Callable[[Any], bool]


SLOTS: dict[str, Slot] = {s.name: s for s in (
    Slot("recent", "the epoch's datasets, one per input (list of Dataset)", _list_of(Dataset)),
    Slot("epoch", "what a stage may know of the epoch (EpochInfo)", lambda v: isinstance(v, EpochInfo)),
    Slot("reference", "the composite of the previous epoch (Composite)", lambda v: isinstance(v, Composite)),
    Slot("registration", "the transform applied to the recent data (Registration)",
         lambda v: isinstance(v, Registration)),
    Slot("rov", "the region of view of the recent data (RegionOfView)", lambda v: isinstance(v, RegionOfView)),
    Slot("correspondences", "per recent dataset, its candidate matches (list of Correspondences)",
         _list_of(Correspondences)),
    Slot("scores", "per recent dataset, a dissimilarity per element (list of Scores)", _list_of(Scores)),
    Slot("change", "per recent dataset, a change mask and state per element (list of Change)", _list_of(Change)),
    Slot("composite", "the twin after this epoch (Composite)", lambda v: isinstance(v, Composite)),
)}


def valid(slot: str, value: Any) -> bool:
    """Whether ``value`` is what the engine's slot ``slot`` holds (True for slots the engine does not know)."""
    known = SLOTS.get(slot)
    return known is None or known.check(value)
