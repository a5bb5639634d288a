"""``bhattacharyya``: BD = −ln ∫√(p₁p₂) for every pair of uncertainty models (closed forms where they exist,
numerical integration with a reported tolerance ε_T otherwise; the mathematics is ``bhattacharyya_maths``)."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt

from gdt_pipeline.measures import Counts, Measured, PairGroup, distance_stage

from .bhattacharyya_maths import bd_gauss_gauss, bhattacharyya

VERSION = "1.2.0"
bhattacharyya_gaussian = bd_gauss_gauss  # the closed form, kept under its descriptive name


class BhattacharyyaParams(BaseModel):
    """Parameters of the Bhattacharyya distance."""

    model_config = ConfigDict(extra="forbid")
    epsilon: PositiveFloat = Field(1e-6, description="Tolerance ε_T on the coefficient BC for numerically "
                                                     "integrated pairs (Gaussian–turned box: Genz quadrature).")
    samples: PositiveInt = Field(4096, description="Importance samples per pair where no quadrature applies "
                                                   "(mixtures, turned box pairs); their error is reported.")
    non_gaussian: Literal["exact", "moment_match"] = Field(
        "exact", description="exact: integrate every family pair; moment_match: replace boxes and mixtures by the "
                             "Gaussian of equal covariance first (faster, approximate).")


def bhattacharyya_pairs(g: PairGroup, rng: np.random.Generator, p: BhattacharyyaParams) -> Measured:
    """BD of each pair of the group, its integration error, and the pairs per method and per Gaussian–box path."""
    u_q, u_r = g.u_q, g.u_r
    if p.non_gaussian == "moment_match":
        n = len(g.idx)
        u_q, u_r = u_q.moment_matched(n), u_r.moment_matched(n)
    paths: dict[str, int] = {}
    bd, err, method = bhattacharyya(g.mu_q, u_q, g.mu_r, u_r, rng=rng, eps=p.epsilon, samples=p.samples, paths=paths)
    return Measured(bd, None, err, {"methods": {method: len(g.idx)}, "paths": paths})


def _summary(counts: Counts) -> dict[str, Any]:
    """The methods used, the Gaussian–box pairs and the share of them per integration path."""
    paths = counts.get("paths", {})
    total = sum(paths.values())
    return {"methods": sorted(counts.get("methods", {})), "gaussian_box_pairs": total,
            "path_shares": {k: round(v / total, 6) for k, v in sorted(paths.items())} if total else {}}


SPEC = distance_stage(name="bhattacharyya", measure=bhattacharyya_pairs, params=BhattacharyyaParams,
                      version=VERSION, tolerance=lambda p: p.epsilon, summary=_summary,
                      description="Bhattacharyya distance for every pair of families (closed forms, quadrature, "
                                  "importance sampling; ε_T reported).")
