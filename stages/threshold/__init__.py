"""Thresholds. Here ``fixed``: an element is changed when its score exceeds τ, or when it has no correspondence
(it then comes in as new, never silently dropped)."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat

from gdt_pipeline import Change, ChangeState, StageContext, StageSpec, hookimpl


class FixedParams(BaseModel):
    """Parameters of the fixed threshold."""

    model_config = ConfigDict(extra="forbid")
    tau: PositiveFloat = Field(description="Change threshold τ on the score (same units as the distance measure).")


def _fixed(ctx: StageContext) -> dict[str, Any]:
    out = []
    for s in ctx["scores"]:
        mask = ~(s.score <= ctx.params.tau)  # NaN (no correspondence) counts as changed
        state = np.where(mask, ChangeState.NEW, ChangeState.UNCHANGED).astype(np.uint8)
        out.append(Change(query=s.query, score=s.score, mask=mask, state=state))
    return {"change": out}


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in thresholds."""
    return [StageSpec(name="fixed", family="threshold", version="1.0.0", params=FixedParams, run=_fixed,
                      requires=("scores",), provides=("change",), description="Changed where score > τ.")]
