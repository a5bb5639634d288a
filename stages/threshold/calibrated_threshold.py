"""``calibrated_threshold`` (the issue's "calibrated"; the name ``calibrated`` is the uncertainty estimator's): τ for a
chosen false-alarm rate, from the scores of simulated unchanged pairs drawn from the two actual uncertainty models
(seeded); the rate achieved on an independent simulation is reported, with the models it drew from. A model with a
heavy tail (a Student t from ``gdt calibrate``) is drawn with its tail, so τ and the achieved rate carry it: on the
real bunny scans a Gaussian null put τ too low and flagged 1.6 % of the scored points at a 1 % setting."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveInt

from gdt_pipeline import Scores, StageContext, family_stage

from .cut import above, change_of, decided


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


def _models(scores: list[Scores]) -> list[str]:
    """The pairs of models the null simulation of ``scores`` draws from (as its simulators name them)."""
    return sorted({m for s in scores for m in getattr(s.simulate, "models", ["unnamed"])})


def _decided(members: list[Scores]) -> dict[str, int]:
    """The decided elements of ``members``, summed (``cut.decided``)."""
    total: dict[str, int] = {}
    for s in members:
        for key, n in decided(s).items():
            total[key] = total.get(key, 0) + n
    return total


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
            out += [change_of(s, np.ones(len(s.score), bool), None) for s in members]
            continue
        tau = float(np.quantile(null, 1.0 - p.false_alarm))
        achieved = float(np.mean(simulate(ctx.rng, p.samples) > tau))
        models = _models(members)
        ctx.log.info("calibrated tau %.6g for false alarms %.4g (%s): achieved %.4g on an independent simulation "
                     "drawn from %s", tau, p.false_alarm, query, achieved, "; ".join(models))
        counts = _decided(members)
        judged = counts["scored"] + counts["new_without_correspondence"]
        # every decided element counts: one without a correspondence is changed whatever τ is, so on unchanged data
        # it is a false alarm as surely as a score above τ
        overall = (achieved * counts["scored"] + counts["new_without_correspondence"]) / judged if judged else 0.0
        report.append({"query": query, "tau": tau, "false_alarm_target": p.false_alarm,
                       "false_alarm_achieved": overall, "false_alarm_simulated": achieved, "decided": counts,
                       "samples": int(p.samples), "null_models": models})
        out += [change_of(s, above(s.score, tau), tau) for s in members]
    ctx.report(calibration=report)
    return {"change": out}


SPEC = family_stage("threshold", name="calibrated_threshold", version="1.4.0", params=CalibratedParams,
                    run=_calibrated,
                    description="τ for a false-alarm rate, from simulated unchanged pairs of the actual models.")
