"""The composite the twin holds after an epoch: its items, segments (the twin store's ``Segment``), and what a stage
knows of the epoch."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin_store import Segment

from .arrays import frozen_array
from .data import Dataset
from .states import ChangeState, Role


@dataclass(frozen=True)
class CompositeItem:
    """One dataset held in the twin with its per-element state: what the twin stores as one prim.

    ``state`` (uint8 ChangeState codes), ``score`` (NaN = not scored), ``source_epoch`` (index of the epoch that
    supplied each element), ``visible`` (the element is part of the composite now; hidden elements stay in the
    history), ``reason`` (uint8 FusionReason codes, default baseline) and ``reason_ratio`` (the fusion rule's
    √det Σ ratio, NaN where none) are all arrays over the dataset's elements.
    """

    key: str
    dataset: Dataset
    epoch: str
    state: np.ndarray
    score: np.ndarray
    source_epoch: np.ndarray
    visible: np.ndarray
    p_value: np.ndarray | None = None
    reason: np.ndarray | None = None
    reason_ratio: np.ndarray | None = None
    area_seen: np.ndarray | None = None  # share of each element's area a station saw (NaN: not judged by area)
    area_removed: np.ndarray | None = None  # share of each element's area seen through, i.e. removed

    def __post_init__(self) -> None:
        n = self.dataset.n_elements
        reason = np.zeros(n, np.uint8) if self.reason is None else self.reason
        object.__setattr__(self, "reason", frozen_array(reason, np.uint8, (n,), f"{self.key}: fusion reason"))
        ratio = np.full(n, np.nan) if self.reason_ratio is None else self.reason_ratio
        object.__setattr__(self, "reason_ratio", frozen_array(ratio, np.float64, (n,), f"{self.key}: fusion ratio"))
        if self.p_value is not None:
            object.__setattr__(self, "p_value", frozen_array(self.p_value, np.float64, (n,), f"{self.key}: p-value"))
        for name in ("area_seen", "area_removed"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, frozen_array(getattr(self, name), np.float64, (n,),
                                                            f"{self.key}: {name}"))
        object.__setattr__(self, "state", frozen_array(self.state, np.uint8, (n,), f"{self.key}: state"))
        object.__setattr__(self, "score", frozen_array(self.score, np.float64, (n,), f"{self.key}: score"))
        object.__setattr__(self, "source_epoch", frozen_array(self.source_epoch, np.int32, (n,), f"{self.key}: source"))
        object.__setattr__(self, "visible", frozen_array(self.visible, np.bool_, (n,), f"{self.key}: visible"))


@dataclass(frozen=True)
class Composite:
    """The composite 3D image after an epoch: every item the twin holds, visible or hidden, and the segments of
    what this epoch changed. ``retired`` names the sets the twin keeps that have no visible element left (a hidden
    element never comes back, so they never change again and are not handed to later epochs), each with how many of
    its elements left as removed."""

    items: tuple[CompositeItem, ...] = ()
    segments: tuple[Segment, ...] = ()
    retired: tuple[tuple[str, int], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "items", tuple(self.items))
        object.__setattr__(self, "segments", tuple(self.segments))
        object.__setattr__(self, "retired", tuple(self.retired))
        keys = [it.key for it in self.items]
        if len(set(keys)) != len(keys):
            raise ValueError(f"composite has duplicate item keys: {sorted(k for k in set(keys) if keys.count(k) > 1)}")

    def counts(self) -> dict[str, int]:
        """Number of visible elements per change state name, over all items; "removed" counts the hidden elements
        marked removed."""
        out = {s.name.lower(): 0 for s in ChangeState}
        for it in self.items:
            codes = np.bincount(it.state[it.visible], minlength=len(ChangeState))
            for s in ChangeState:
                out[s.name.lower()] += int(codes[s])
            # removed elements leave the composite (hidden) but are what an epoch reports
            out["removed"] += int(np.sum((it.state == ChangeState.REMOVED) & ~it.visible))
        out["removed"] += sum(n for _, n in self.retired)
        return out


@dataclass(frozen=True)
class EpochInfo:
    """What a stage may know about the epoch it runs in."""

    id: str
    index: int
    role: Role
    seed: int
    workflow_dir: Path
    units: str = "m"
    # a point near the epoch's data, the same for the whole epoch and every tile of it: the origin stages subtract
    # before sums that round (normals from neighbourhoods), so that a tile computes bit for bit what the epoch does
    origin: tuple[float, float, float] | None = None
