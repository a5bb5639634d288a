"""What every threshold does with its cut: the change of a dataset's scores, with NaN (no correspondence) changed."""

from __future__ import annotations

import numpy as np

from gdt_pipeline import Change, ChangeState, Scores


def change_of(s: Scores, mask: np.ndarray, threshold: float | None) -> Change:
    """The change of a dataset's scores under ``mask``: changed elements new, the rest unchanged."""
    state = np.where(mask, ChangeState.NEW, ChangeState.UNCHANGED).astype(np.uint8)
    return Change(query=s.query, score=s.score, mask=mask, state=state, p_value=s.p_value, threshold=threshold)


def above(score: np.ndarray, tau: float) -> np.ndarray:
    """Changed where the score exceeds τ."""
    return ~(score <= tau)  # NaN (no correspondence) counts as changed
