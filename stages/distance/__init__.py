"""Distance measures. Here ``bhattacharyya`` for Gaussian pairs in closed form (paper Sec. 4.2.1):

    BD = 1/8 dᵀ Σ⁻¹ d + 1/2 ln( det Σ / sqrt(det Σ₁ det Σ₂) ),   Σ = (Σ₁ + Σ₂) / 2,  d = μ₂ − μ₁

Non-Gaussian families (tolerance boxes) are refused unless ``non_gaussian: moment_match`` replaces them by the
Gaussian of the same covariance, an approximation recorded in provenance; the exact box pairs come with the distance
issue."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gdt_pipeline import Dataset, GaussianUncertainty, Scores, StageContext, StageSpec, hookimpl


class BhattacharyyaParams(BaseModel):
    """Parameters of the Gaussian Bhattacharyya distance."""

    model_config = ConfigDict(extra="forbid")
    non_gaussian: Literal["error", "moment_match"] = Field(
        "error", description="What to do with a non-Gaussian uncertainty: stop with an error, or use the Gaussian "
                             "with the same covariance (an approximation).")


def bhattacharyya_gaussian(mu1: np.ndarray, cov1: np.ndarray, mu2: np.ndarray, cov2: np.ndarray) -> np.ndarray:
    """Bhattacharyya distance between Gaussians, vectorised over ``(N,3)`` means and ``(N,3,3)`` covariances."""
    cov = 0.5 * (cov1 + cov2)
    d = (mu2 - mu1)[..., None]
    # Cholesky both solves and gives log-determinants stably for nearly singular (flat) covariances.
    chol = np.linalg.cholesky(cov)
    y = np.linalg.solve(chol, d)[..., 0]
    maha = np.einsum("ni,ni->n", y, y)
    logdet = 2.0 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(axis=1)
    _, ld1 = np.linalg.slogdet(cov1)
    _, ld2 = np.linalg.slogdet(cov2)
    return maha / 8.0 + 0.5 * (logdet - 0.5 * (ld1 + ld2))


def _covariances(ds: Dataset, idx: np.ndarray, policy: str, role: str) -> np.ndarray:
    unc = ds.uncertainty
    if unc is None:
        raise ValueError(f"{role} dataset {ds.name!r} has no uncertainty: add an uncertainty stage before this one")
    if not isinstance(unc, GaussianUncertainty) and policy == "error":
        raise ValueError(f"{role} dataset {ds.name!r} has a {unc.family!r} uncertainty; the closed form needs "
                         f"Gaussians (set `non_gaussian: moment_match` to use the Gaussian of equal covariance)")
    return unc.covariance(ds.n_elements)[idx]


def _bhattacharyya(ctx: StageContext) -> dict[str, Any]:
    recent, reference, corr = ctx["recent"], ctx["reference"], ctx["correspondences"]
    policy = ctx.params.non_gaussian
    out = []
    for c in corr:
        ds = recent[c.query]
        score = np.full(ds.n_elements, np.nan)
        found = np.flatnonzero(c.found)
        if found.size:
            cov_q = _covariances(ds, found, policy, "recent")
            mu_q = ds.element_positions()[found]
            cov_r = np.empty_like(cov_q)
            items = c.ref_item[found]
            for it in np.unique(items):
                sel = items == it
                ref_ds = reference.items[it].dataset
                cov_r[sel] = _covariances(ref_ds, c.ref_element[found][sel], policy, "reference")
            score[found] = bhattacharyya_gaussian(mu_q, cov_q, c.position[found], cov_r)
        out.append(Scores(query=c.query, score=score, measure="bhattacharyya"))
    return {"scores": out}


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in distance measures."""
    return [StageSpec(name="bhattacharyya", family="distance", version="1.0.0", params=BhattacharyyaParams,
                      run=_bhattacharyya, requires=("recent", "reference", "correspondences"), provides=("scores",),
                      description="Bhattacharyya distance between Gaussian uncertainties, closed form.")]
