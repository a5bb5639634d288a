"""The thresholds that cut each dataset's scores by a rule of the workflow's: ``fixed`` (score > τ),
``tolerance_multiple`` (τ = k·ε_T, the paper's initial value) and ``significance`` (p < α)."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat

from gdt_pipeline import StageContext, family_stage

from .cut import above, change_of, relabel_not_comparable


class FixedParams(BaseModel):
    """Parameters of the fixed threshold."""

    model_config = ConfigDict(extra="forbid")
    tau: PositiveFloat = Field(description="Change threshold τ on the score (same units as the distance measure).")


def _fixed(ctx: StageContext) -> dict[str, Any]:
    return {"change": [change_of(s, above(s.score, ctx.params.tau), ctx.params.tau) for s in ctx["scores"]]}


class ToleranceMultipleParams(BaseModel):
    """τ = k·ε_T."""

    model_config = ConfigDict(extra="forbid")
    k: PositiveFloat = Field(description="Multiple of the distance stage's integration tolerance ε_T.")


def _tolerance_multiple(ctx: StageContext) -> dict[str, Any]:
    out = []
    for s in ctx["scores"]:
        if s.tolerance is None:
            raise ValueError(f"measure {s.measure!r} reports no integration tolerance ε_T; tolerance_multiple needs "
                             f"one (bhattacharyya reports it)")
        tau = ctx.params.k * s.tolerance
        out.append(change_of(s, above(s.score, tau), tau))
    ctx.report(tau=[c.threshold for c in out])
    return {"change": out}


class SignificanceParams(BaseModel):
    """Cut on the p-value of a test."""

    model_config = ConfigDict(extra="forbid")
    alpha: float = Field(0.01, gt=0, lt=1, description="Changed where p < alpha.")


def _significance(ctx: StageContext) -> dict[str, Any]:
    out = []
    for s in ctx["scores"]:
        if s.p_value is None and not np.isnan(s.score).all():
            raise ValueError(f"measure {s.measure!r} gives no p-values; significance needs a test "
                             f"(hotelling, welch_m3c2)")
        # NaN (no correspondence) counts as changed; so does every element of a dataset (or tile) with no pair at
        # all, of which no measure can say whether it would have given p-values
        p_value = np.full(len(s.score), np.nan) if s.p_value is None else s.p_value
        mask = ~(p_value >= ctx.params.alpha)
        out.append(change_of(s, mask, None))
    return {"change": out}


FIXED = family_stage("threshold", name="fixed", version="1.3.0", params=FixedParams, run=_fixed, tiling="tile",
                     finish=relabel_not_comparable, description="Changed where score > τ.")
TOLERANCE_MULTIPLE = family_stage("threshold", name="tolerance_multiple", version="1.3.0",
                                  params=ToleranceMultipleParams, run=_tolerance_multiple,
                                  description="τ = k·ε_T, the paper's initial value.")
SIGNIFICANCE = family_stage("threshold", name="significance", version="1.3.0", params=SignificanceParams,
                            run=_significance, tiling="tile", finish=relabel_not_comparable,
                            description="Changed where the test's p-value < α.")
