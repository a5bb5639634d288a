"""History queries over a twin's epochs: one entry per epoch, and what changed per element set between two."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .elements import ElementSet
from .names import STATE_NAMES


@dataclass(frozen=True)
class EpochEntry:
    """One epoch of a twin's history: its id and place, its visible elements per change state, and the provenance
    its layer records (as stored; ``gdt_pipeline.provenance.EpochProvenance.from_dict`` reads it)."""

    id: str
    index: int
    counts: dict[str, int] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SetDiff:
    """How one element set changed between two epochs."""

    key: str
    kind: str
    added: bool
    elements: int
    came_in: int
    went_out: int
    transitions: dict = field(default_factory=dict)
    visible: dict = field(default_factory=dict)


def set_diff(old: ElementSet | None, es: ElementSet) -> SetDiff:
    """How ``es`` differs from the same set at an earlier epoch (``old``; None when the set is new)."""
    vis_b = np.asarray(es.visible, dtype=bool)
    vis_a = np.zeros_like(vis_b) if old is None else np.asarray(old.visible, dtype=bool)
    transitions: dict[str, int] = {}
    if old is not None:
        moved = old.state != es.state
        pairs, counts = np.unique(np.stack([old.state[moved], es.state[moved]], axis=1), axis=0,
                                  return_counts=True)
        for (a, b), c in zip(pairs.tolist(), counts.tolist(), strict=True):
            transitions[f"{STATE_NAMES[a]}->{STATE_NAMES[b]}"] = int(c)
    visible_states = np.bincount(es.state[vis_b], minlength=len(STATE_NAMES))
    return SetDiff(key=es.key, kind=es.kind, added=old is None, elements=es.n_elements,
                   came_in=int(np.sum(vis_b & ~vis_a)), went_out=int(np.sum(vis_a & ~vis_b)),
                   transitions=transitions, visible=dict(zip(STATE_NAMES, map(int, visible_states), strict=True)))


def count_states(elements: Sequence[ElementSet]) -> dict[str, int]:
    """Visible elements per change state, over all sets."""
    total = np.zeros(len(STATE_NAMES), dtype=np.int64)
    for es in elements:
        total += np.bincount(es.state[np.asarray(es.visible, dtype=bool)], minlength=len(STATE_NAMES))
    return dict(zip(STATE_NAMES, map(int, total), strict=True))
