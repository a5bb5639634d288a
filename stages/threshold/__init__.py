"""Thresholds: turn scores into a change mask. An element with no correspondence (NaN score) is always changed: it
comes in as new, never silently dropped.

- ``fixed``: changed where score > τ;
- ``tolerance_multiple``: τ = k·ε_T, the paper's initial value, with ε_T the integration tolerance the distance
  stage reports;
- ``significance``: changed where the test's p-value < α (for measures that have p-values: hotelling, welch_m3c2);
- ``calibrated_threshold`` (the issue's "calibrated"; the name ``calibrated`` is the uncertainty estimator's):
  τ for a chosen false-alarm rate, from the scores of simulated unchanged pairs drawn from the two
  actual uncertainty models (seeded); the rate achieved on an independent simulation is reported.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt

from gdt_pipeline import Change, ChangeState, Scores, StageContext, StageSpec, hookimpl


def _change(s: Scores, mask: np.ndarray, threshold: float | None) -> Change:
    state = np.where(mask, ChangeState.NEW, ChangeState.UNCHANGED).astype(np.uint8)
    return Change(query=s.query, score=s.score, mask=mask, state=state, p_value=s.p_value, threshold=threshold)


def _above(score: np.ndarray, tau: float) -> np.ndarray:
    return ~(score <= tau)  # NaN (no correspondence) counts as changed


class FixedParams(BaseModel):
    """Parameters of the fixed threshold."""

    model_config = ConfigDict(extra="forbid")
    tau: PositiveFloat = Field(description="Change threshold τ on the score (same units as the distance measure).")


def _fixed(ctx: StageContext) -> dict[str, Any]:
    return {"change": [_change(s, _above(s.score, ctx.params.tau), ctx.params.tau) for s in ctx["scores"]]}


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
        out.append(_change(s, _above(s.score, tau), tau))
    ctx.report(tau=[c.threshold for c in out])
    return {"change": out}


class SignificanceParams(BaseModel):
    """Cut on the p-value of a test."""

    model_config = ConfigDict(extra="forbid")
    alpha: float = Field(0.01, gt=0, lt=1, description="Changed where p < alpha.")


def _significance(ctx: StageContext) -> dict[str, Any]:
    out = []
    for s in ctx["scores"]:
        if s.p_value is None:
            raise ValueError(f"measure {s.measure!r} gives no p-values; significance needs a test "
                             f"(hotelling, welch_m3c2)")
        mask = ~(s.p_value >= ctx.params.alpha)  # NaN (no correspondence) counts as changed
        out.append(_change(s, mask, None))
    return {"change": out}


class CalibratedParams(BaseModel):
    """τ from simulated unchanged pairs, for a chosen false-alarm rate."""

    model_config = ConfigDict(extra="forbid")
    false_alarm: float = Field(0.01, gt=0, lt=0.5, description="Share of unchanged elements allowed to be flagged.")
    samples: PositiveInt = Field(50_000, description="Simulated unchanged pairs used to set τ (and again, "
                                                      "independently, to check the rate achieved).")
    per: Literal["dataset", "epoch"] = Field(
        "dataset", description="dataset: one τ per recent dataset, each from its own `samples` pairs; epoch: one τ "
                               "for all of the epoch's datasets, from `samples` pairs drawn across them in "
                               "proportion to their sizes (for many scans of one sensor: the cost does not grow "
                               "with the number of scans).")


def _pooled(ctx: StageContext, scores: list[Scores]) -> dict[str, Any]:
    """One τ for the epoch: the simulated null pairs drawn over all datasets in proportion to their elements."""
    p = ctx.params
    if any(s.simulate is None for s in scores):
        bad = next(s for s in scores if s.simulate is None)
        raise ValueError(f"measure {bad.measure!r} cannot simulate unchanged pairs; use fixed or significance")
    sizes = np.array([np.isfinite(s.score).sum() for s in scores], dtype=np.float64)
    if not scores or sizes.sum() == 0:
        return {"change": [_change(s, np.ones(len(s.score), bool), None) for s in scores]}

    def draw() -> np.ndarray:
        counts = ctx.rng.multinomial(p.samples, sizes / sizes.sum())
        return np.concatenate([s.simulate(ctx.rng, int(n)) for s, n in zip(scores, counts, strict=True) if n])

    null = draw()
    tau = float(np.quantile(null, 1.0 - p.false_alarm))
    achieved = float(np.mean(draw() > tau))
    ctx.log.info("calibrated tau %.6g over %d datasets for false alarms %.4g: achieved %.4g on an independent "
                 "simulation", tau, len(scores), p.false_alarm, achieved)
    ctx.report(calibration=[{"query": [s.query for s in scores], "tau": tau, "false_alarm_target": p.false_alarm,
                             "false_alarm_achieved": achieved, "samples": int(p.samples)}])
    return {"change": [_change(s, _above(s.score, tau), tau) for s in scores]}


def _calibrated(ctx: StageContext) -> dict[str, Any]:
    p = ctx.params
    if p.per == "epoch":
        return _pooled(ctx, list(ctx["scores"]))
    out, report = [], []
    for s in ctx["scores"]:
        if s.simulate is None:
            raise ValueError(f"measure {s.measure!r} cannot simulate unchanged pairs; use fixed or significance")
        null = s.simulate(ctx.rng, p.samples)
        if null.size == 0:
            out.append(_change(s, np.ones(len(s.score), bool), None))
            continue
        tau = float(np.quantile(null, 1.0 - p.false_alarm))
        check = s.simulate(ctx.rng, p.samples)
        achieved = float(np.mean(check > tau))
        ctx.log.info("calibrated tau %.6g for false alarms %.4g: achieved %.4g on an independent simulation", tau,
                     p.false_alarm, achieved)
        report.append({"query": s.query, "tau": tau, "false_alarm_target": p.false_alarm,
                       "false_alarm_achieved": achieved, "samples": int(p.samples)})
        out.append(_change(s, _above(s.score, tau), tau))
    ctx.report(calibration=report)
    return {"change": out}


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in thresholds."""
    common = {"family": "threshold", "version": "1.2.0", "requires": ("scores",), "provides": ("change",)}
    return [
        StageSpec(name="fixed", params=FixedParams, run=_fixed, description="Changed where score > τ.", **common),
        StageSpec(name="tolerance_multiple", params=ToleranceMultipleParams, run=_tolerance_multiple,
                  description="τ = k·ε_T, the paper's initial value.", **common),
        StageSpec(name="significance", params=SignificanceParams, run=_significance,
                  description="Changed where the test's p-value < α.", **common),
        StageSpec(name="calibrated_threshold", params=CalibratedParams, run=_calibrated,
                  description="τ for a false-alarm rate, from simulated unchanged pairs of the actual models.",
                  **common),
    ]
