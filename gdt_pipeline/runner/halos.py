"""Each tile's halo from the reach of the elements it serves (``docs/scale.md``, "Halos").

A stage's ``reach`` may be one figure for the epoch or one per recent element: how far its data reach for an epoch
whose every element were like this one. A tile's reach of stage k is then the largest over every element within
the widest reach of stages k, k+1, ... of its core: the elements whose data, or whose neighbours' data, its core can
need. So one grazing ToF point widens the halos of the tiles near it only, not of the whole epoch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import GdtError
from ..tiling import CellIndex
from .plan import StagePlan


@dataclass(frozen=True)
class StageReach:
    """One stage's reach: its largest, and per recent dataset its elements' (None: the largest everywhere)."""

    widest: float
    per_dataset: tuple[np.ndarray | None, ...]


def stage_reaches(stages: list[StagePlan], slots: dict[str, Any]) -> list[StageReach]:
    """Each stage's declared reach, checked (0 without one)."""
    n_sets = len(slots["recent"])
    out = []
    for st in stages:
        value = 0.0 if st.spec.reach is None else st.spec.reach(st.params, slots)
        per = _per_dataset(st.spec.name, value, [ds.n_elements for ds in slots["recent"]])
        widest = max((float(p.max()) for p in per if p is not None and len(p)),
                     default=0.0 if _per_element(value) else float(value))  # type: ignore[arg-type]
        if not np.isfinite(widest) or widest < 0:
            raise GdtError(f"stage {st.spec.name!r} declared a reach of {widest}; it cannot run in tiles")
        out.append(StageReach(widest, per if per else (None,) * n_sets))
    return out


def _per_element(value: object) -> bool:
    """Whether a declared reach is one array per dataset (a list or tuple), not one figure (a float, a numpy scalar
    or a 0-d array: ``np.ndim`` would try to stack a ragged list)."""
    return isinstance(value, (list, tuple))


def _per_dataset(name: str, value: float | Sequence[np.ndarray], sizes: list[int]) -> tuple[np.ndarray | None, ...]:
    if not _per_element(value):
        return ()
    per = tuple(np.asarray(v, dtype=np.float64) for v in value)  # type: ignore[union-attr]
    if [len(p) for p in per] != sizes:
        raise GdtError(f"stage {name!r} declared a reach per element for {[len(p) for p in per]} elements of the "
                       f"recent datasets, which hold {sizes}")
    if any(len(p) and not np.all(np.isfinite(p) & (p >= 0)) for p in per):
        raise GdtError(f"stage {name!r} declared a reach that is not a finite distance ≥ 0; it cannot run in tiles")
    return per


def tile_reaches(reaches: list[StageReach], lower: np.ndarray, upper: np.ndarray,
                 indexes: list[CellIndex]) -> list[float]:
    """Per stage, its reach for the tile with core box [lower, upper]."""
    out = []
    for k, reach in enumerate(reaches):
        grow = sum(r.widest for r in reaches[k:])
        widest = 0.0
        for per, index in zip(reach.per_dataset, indexes, strict=True):
            if per is None:
                widest = reach.widest
                break
            ids = index.query(lower - grow, upper + grow)
            if len(ids):
                widest = max(widest, float(per[ids].max()))
        out.append(widest)
    return out
