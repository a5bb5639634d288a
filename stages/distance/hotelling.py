"""``hotelling``: T² = dᵀ(Σ₁+Σ₂)⁻¹d with p-values from χ²(3), for Gaussians only (the test holds only for normals)."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict

from gdt_pipeline import GaussianUncertainty
from gdt_pipeline.geometry import quad_inv3
from gdt_pipeline.measures import MeasureResult, PairGroup, distance_stage


class HotellingParams(BaseModel):
    """Hotelling's T² with known covariances has no parameters."""

    model_config = ConfigDict(extra="forbid")


def hotelling(g: PairGroup, rng: np.random.Generator, params: HotellingParams | None = None) -> MeasureResult:
    """Hotelling's T² of each pair with known covariances, and its p-value from χ²(3) (Gaussians only)."""
    for u, role in ((g.u_q, "recent"), (g.u_r, "reference")):
        if not isinstance(u, GaussianUncertainty):
            raise ValueError(f"{role} data has a {u.model!r} uncertainty: Hotelling's T² holds only for normal "
                             f"distributions (paper Sec. 4.2.1); use bhattacharyya for other families")
    n = len(g.idx)
    t2 = quad_inv3(g.u_q.covariance(n) + g.u_r.covariance(n), g.mu_q - g.mu_r)
    from scipy.stats import chi2  # here: scipy.stats takes a third of a second to import, and most runs need none

    return t2, chi2.sf(t2, 3), np.zeros(0)


SPEC = distance_stage(name="hotelling", measure=hotelling, params=HotellingParams, version="1.2.0",
                      description="Hotelling's T² with known covariances, p-values from χ²(3) (Gaussians only).")
