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

from collections.abc import Callable
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


def _pooled(scores: list[Scores]) -> Callable[[np.random.Generator, int], np.ndarray]:
    """A simulator of the whole epoch: ``n`` null pairs drawn over all datasets in proportion to their elements."""
    sizes = np.array([np.isfinite(s.score).sum() for s in scores], dtype=np.float64)

    def simulate(rng: np.random.Generator, n: int) -> np.ndarray:
        if sizes.sum() == 0:
            return np.zeros(0)
        counts = rng.multinomial(n, sizes / sizes.sum())
        return np.concatenate([s.simulate(rng, int(k)) for s, k in zip(scores, counts, strict=True) if k])

    return simulate


def _calibrated(ctx: StageContext) -> dict[str, Any]:
    p = ctx.params
    scores = list(ctx["scores"])
    for s in scores:
        if s.simulate is None:
            raise ValueError(f"measure {s.measure!r} cannot simulate unchanged pairs; use fixed or significance")
    # one τ per dataset from its own pairs, or one for the epoch from pairs drawn across all of them
    groups = [([s], s.simulate, s.query) for s in scores] if p.per == "dataset" else \
        [(scores, _pooled(scores), [s.query for s in scores])] if scores else []
    out, report = [], []
    for members, simulate, query in groups:
        null = simulate(ctx.rng, p.samples)
        if null.size == 0:
            out += [_change(s, np.ones(len(s.score), bool), None) for s in members]
            continue
        tau = float(np.quantile(null, 1.0 - p.false_alarm))
        achieved = float(np.mean(simulate(ctx.rng, p.samples) > tau))
        ctx.log.info("calibrated tau %.6g for false alarms %.4g (%s): achieved %.4g on an independent simulation",
                     tau, p.false_alarm, query, achieved)
        report.append({"query": query, "tau": tau, "false_alarm_target": p.false_alarm,
                       "false_alarm_achieved": achieved, "samples": int(p.samples)})
        out += [_change(s, _above(s.score, tau), tau) for s in members]
    ctx.report(calibration=report)
    return {"change": out}


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in thresholds."""
    common = {"family": "threshold", "version": "1.2.0", "requires": ("scores",), "provides": ("change",)}
    return [
        StageSpec(name="fixed", params=FixedParams, run=_fixed, description="Changed where score > τ.",
                  tiling="tile", **common),
        StageSpec(name="tolerance_multiple", params=ToleranceMultipleParams, run=_tolerance_multiple,
                  description="τ = k·ε_T, the paper's initial value.", **common),
        StageSpec(name="significance", params=SignificanceParams, run=_significance,
                  description="Changed where the test's p-value < α.", tiling="tile", **common),
        StageSpec(name="calibrated_threshold", params=CalibratedParams, run=_calibrated,
                  description="τ for a false-alarm rate, from simulated unchanged pairs of the actual models.",
                  **common),
    ]
