"""What every threshold does with its cut: the change of a dataset's scores, with NaN (no correspondence) changed:
new where the reference covers the place, not comparable elsewhere."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from gdt_pipeline import Change, ChangeState, Scores, StageContext


def change_of(s: Scores, mask: np.ndarray, threshold: float | None) -> Change:
    """The change of a dataset's scores under ``mask``: changed elements new, the rest unchanged, and the elements
    without a score where the reference has no data not comparable (they still come in: changed)."""
    state = np.where(mask, ChangeState.NEW, ChangeState.UNCHANGED).astype(np.uint8)
    apart = not_comparable(s)
    state[apart] = ChangeState.NOT_COMPARABLE
    mask = mask | apart
    return Change(query=s.query, score=s.score, mask=mask, state=state, p_value=s.p_value, threshold=threshold)


def above(score: np.ndarray, tau: float) -> np.ndarray:
    """Changed where the score exceeds τ."""
    return ~(score <= tau)  # NaN (no correspondence) counts as changed


def not_comparable(s: Scores) -> np.ndarray:
    """The elements without a score where the reference has no data (none before the coverage is judged)."""
    return np.isnan(s.score) & ~(np.ones(len(s.score), bool) if s.covered is None else s.covered)


def decided(s: Scores) -> dict[str, int]:
    """What a threshold decides about a dataset's elements: scored, new for want of a correspondence where the
    reference covers their place, and not comparable (no reference data there)."""
    unscored, apart = np.isnan(s.score), not_comparable(s)
    return {"scored": int((~unscored).sum()), "new_without_correspondence": int((unscored & ~apart).sum()),
            "not_comparable": int(apart.sum())}


def relabel_not_comparable(ctx: StageContext) -> dict[str, Any]:
    """A tiled threshold's ``finish``: the distance stage judges coverage over the whole epoch after its tiles, so
    the elements without a score where the reference has no data become not comparable here."""
    scores = {s.query: s for s in ctx["scores"]}
    out = []
    for c in ctx["change"]:
        s = scores.get(c.query)
        if s is None or s.covered is None:
            out.append(c)
            continue
        state = c.state.copy()
        apart = not_comparable(s)
        state[apart] = ChangeState.NOT_COMPARABLE
        out.append(dataclasses.replace(c, state=state, mask=c.mask | apart))
    return {"change": out}
