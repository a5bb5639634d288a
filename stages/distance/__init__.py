"""Distance measures (paper Sec. 4.2.1), one score per recent element against its correspondence:

- ``bhattacharyya``: BD = −ln ∫√(p₁p₂) for every pair of families (closed forms where they exist, numerical
  integration with a reported tolerance ε_T otherwise; see ``measures``);
- ``hotelling``: T² = dᵀ(Σ₁+Σ₂)⁻¹d with p-values from χ²(3), for Gaussians only (the test holds only for normals);
- ``welch_m3c2``: the M3C2-style test on equal means along the local normal, with known variances
  (t = nᵀd / √(nᵀΣ₁n + nᵀΣ₂n), two-sided p-value), as a baseline inside the pipeline;
- ``euclidean``: the plain distance, for comparison.

Every stage attaches to its ``Scores`` a ``simulate(rng, n)`` that scores n unchanged pairs drawn from the actual
uncertainty models, which the ``calibrated`` threshold uses.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt
from scipy.special import ndtr
from scipy.stats import chi2

from gdt_pipeline import (
    Composite,
    Correspondences,
    Dataset,
    GaussianUncertainty,
    Scores,
    StageContext,
    StageSpec,
    hookimpl,
)
from gdt_pipeline.geometry import estimate_normals, quad_inv3

from .measures import bd_gauss_gauss, bhattacharyya

bhattacharyya_gaussian = bd_gauss_gauss  # the closed form, kept under its descriptive name


@dataclass(frozen=True)
class PairGroup:
    """Candidate pairs of one recent dataset sharing one reference model: candidate indices, the query elements they
    belong to, means and uncertainties of both sides."""

    idx: np.ndarray
    elements: np.ndarray
    mu_q: np.ndarray
    u_q: Any
    mu_r: np.ndarray
    u_r: Any
    ref_items: np.ndarray
    ref_elements: np.ndarray
    normal: np.ndarray | None = None  # local surface normal per pair, for tests along the normal

    def subset(self, sel: np.ndarray, mu_q: np.ndarray | None = None, mu_r: np.ndarray | None = None) -> PairGroup:
        """The pairs ``sel`` of this group, optionally with other means (simulated ones)."""
        return PairGroup(self.idx[sel], self.elements[sel], self.mu_q[sel] if mu_q is None else mu_q,
                         _take(self.u_q, sel), self.mu_r[sel] if mu_r is None else mu_r, _take(self.u_r, sel),
                         self.ref_items[sel], self.ref_elements[sel], None if self.normal is None else self.normal[sel])


def _rows(u: Any) -> int:
    for name in ("cov", "half_widths", "weights"):
        arr = getattr(u, name, None)
        if arr is not None:
            return arr.shape[0]
    raise TypeError(type(u).__name__)


def _take(u: Any, idx: np.ndarray) -> Any:
    return u if _rows(u) == 1 else u.take(idx)


def pair_groups(ds: Dataset, corr: Correspondences, reference: Composite) -> list[PairGroup]:
    """The candidate pairs of one recent dataset, grouped so that each group has one reference uncertainty model."""
    if ds.uncertainty is None:
        raise ValueError(f"recent dataset {ds.name!r} has no uncertainty: add an uncertainty stage before this one")
    found = np.flatnonzero(corr.found)
    elem = corr.element
    qpos = corr.query_position if corr.query_position is not None else ds.element_positions()[elem]
    groups = []
    if corr.ref_uncertainty is not None:  # per-candidate reference models (mixtures of neighbours)
        over = found[corr.ref_row[found] >= 0]
        if over.size:
            groups.append(PairGroup(over, elem[over], qpos[over], _take(ds.uncertainty, elem[over]),
                                    corr.position[over], _take(corr.ref_uncertainty, corr.ref_row[over]),
                                    corr.ref_item[over], corr.ref_element[over]))
        found = found[corr.ref_row[found] < 0]
    for item in np.unique(corr.ref_item[found]):
        sel = found[corr.ref_item[found] == item]
        ref = reference.items[item].dataset
        if ref.uncertainty is None:
            raise ValueError(f"reference dataset {ref.name!r} has no uncertainty")
        groups.append(PairGroup(sel, elem[sel], qpos[sel], _take(ds.uncertainty, elem[sel]), corr.position[sel],
                                _take(ref.uncertainty, corr.ref_element[sel]), corr.ref_item[sel],
                                corr.ref_element[sel]))
    return groups


def lowest_per_element(elements: np.ndarray, cand_score: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per element, the lowest candidate score (NaN when it has none) and the index of that candidate (−1)."""
    key = np.where(np.isnan(cand_score), np.inf, cand_score)
    order = np.lexsort((key, elements))
    first = np.ones(len(order), dtype=bool)
    first[1:] = elements[order][1:] != elements[order][:-1]
    best = order[first]
    score = np.full(n, np.nan)
    match = np.full(n, -1, dtype=np.int64)
    ok = np.isfinite(key[best])
    score[elements[best[ok]]] = cand_score[best[ok]]
    match[elements[best[ok]]] = best[ok]
    return score, match


Measure = Callable[[PairGroup, np.random.Generator], tuple[np.ndarray, np.ndarray | None, np.ndarray]]


def _sample_offsets(u: Any, n: int, rng: np.random.Generator) -> np.ndarray:
    return u.sample(n, rng, 1)[:, 0, :]


def _simulator(groups: list[PairGroup], measure: Measure) -> Callable[[np.random.Generator, int], np.ndarray]:
    """Scores of unchanged pairs: both measurements of the same true position, each off by its own model's error."""
    sizes = np.array([len(g.idx) for g in groups])

    def simulate(rng: np.random.Generator, n: int) -> np.ndarray:
        if sizes.sum() == 0:
            return np.zeros(0)
        pick = rng.integers(0, sizes.sum(), n)
        owner = np.searchsorted(np.cumsum(sizes), pick, side="right")
        out = []
        for g_i in np.unique(owner):
            g = groups[g_i]
            local = pick[owner == g_i] - (sizes[:g_i].sum() if g_i else 0)
            sub = g.subset(local)
            truth = sub.mu_r
            sim = g.subset(local, mu_q=truth + _sample_offsets(_expand(sub.u_q, len(local)), len(local), rng),
                           mu_r=truth + _sample_offsets(_expand(sub.u_r, len(local)), len(local), rng))
            out.append(measure(sim, rng)[0])
        return np.concatenate(out)

    return simulate


def _expand(u: Any, n: int) -> Any:
    return u if _rows(u) == n else u.take(np.zeros(n, dtype=np.int64))


def _run_measure(ctx: StageContext, name: str, measure: Measure, tolerance: float | None = None,
                 prepare: Callable[[list[PairGroup], int], list[PairGroup]] | None = None) -> dict[str, Any]:
    recent, reference = ctx["recent"], ctx["reference"]
    out = []
    worst = 0.0
    with ctx.progress.task(f"{name} scores", total=len(ctx["correspondences"])) as advance:
        for corr in ctx["correspondences"]:
            ds = recent[corr.query]
            m = len(corr.ref_item)
            cand_score = np.full(m, np.nan)
            cand_p = None
            groups = pair_groups(ds, corr, reference)
            if prepare is not None:
                groups = prepare(groups, corr.query)
            for g in groups:
                s, p, err = measure(g, ctx.rng)
                cand_score[g.idx] = s
                if p is not None:
                    if cand_p is None:
                        cand_p = np.full(m, np.nan)
                    cand_p[g.idx] = p
                if err.size:
                    worst = max(worst, float(np.max(err)))
            score, match = lowest_per_element(corr.element, cand_score, ds.n_elements)
            p_value = None
            if cand_p is not None:
                p_value = np.where(match >= 0, cand_p[np.maximum(match, 0)], np.nan)
            out.append(Scores(query=corr.query, score=score, measure=name, p_value=p_value,
                              tolerance=None if tolerance is None else max(tolerance, worst),
                              simulate=_simulator(groups, measure), match=match))
            advance()
    ctx.report(max_integration_error=worst, tolerance=tolerance)
    return {"scores": out}


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


def _bhattacharyya(ctx: StageContext) -> dict[str, Any]:
    p = ctx.params
    methods: set[str] = set()

    def measure(g: PairGroup, rng: np.random.Generator) -> tuple[np.ndarray, None, np.ndarray]:
        u_q, u_r = g.u_q, g.u_r
        if p.non_gaussian == "moment_match":
            n = len(g.idx)
            u_q = u_q if isinstance(u_q, GaussianUncertainty) else GaussianUncertainty(u_q.covariance(n))
            u_r = u_r if isinstance(u_r, GaussianUncertainty) else GaussianUncertainty(u_r.covariance(n))
        bd, err, method = bhattacharyya(g.mu_q, u_q, g.mu_r, u_r, rng=rng, eps=p.epsilon, samples=p.samples)
        methods.add(method)
        return bd, None, err

    out = _run_measure(ctx, "bhattacharyya", measure, tolerance=p.epsilon)
    ctx.report(methods=sorted(methods))
    return out


class HotellingParams(BaseModel):
    """Hotelling's T² with known covariances has no parameters."""

    model_config = ConfigDict(extra="forbid")


def _hotelling(ctx: StageContext) -> dict[str, Any]:
    def measure(g: PairGroup, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        for u, role in ((g.u_q, "recent"), (g.u_r, "reference")):
            if not isinstance(u, GaussianUncertainty):
                raise ValueError(f"{role} data has a {u.family!r} uncertainty: Hotelling's T² holds only for normal "
                                 f"distributions (paper Sec. 4.2.1); use bhattacharyya for other families")
        n = len(g.idx)
        t2 = quad_inv3(g.u_q.covariance(n) + g.u_r.covariance(n), g.mu_q - g.mu_r)
        return t2, chi2.sf(t2, 3), np.zeros(0)

    return _run_measure(ctx, "hotelling", measure)


class WelchParams(BaseModel):
    """The M3C2-style test along the local normal."""

    model_config = ConfigDict(extra="forbid")
    normal_neighbours: PositiveInt = Field(20, description="Neighbours for point-cloud normals when neither side "
                                                           "is a mesh.")


def _welch(ctx: StageContext) -> dict[str, Any]:
    recent, reference = ctx["recent"], ctx["reference"]

    def with_normals(groups: list[PairGroup], query: int) -> list[PairGroup]:
        ds = recent[query]
        cloud_normals = None
        out = []
        for g in groups:
            ref = reference.items[int(g.ref_items[0])].dataset
            if ds.faces is not None or ref.faces is not None:
                nrm = (ds.facet_normals(g.elements, unit=True) if ds.faces is not None
                       else ref.facet_normals(g.ref_elements, unit=True))
            else:
                if cloud_normals is None:
                    cloud_normals = estimate_normals(ds.points, ctx.params.normal_neighbours)
                nrm = cloud_normals[g.elements]
            out.append(dataclasses.replace(g, normal=nrm))
        return out

    def measure(g: PairGroup, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = len(g.idx)
        along = np.einsum("ij,ij->i", g.normal, g.mu_q - g.mu_r)
        var = np.einsum("ni,nij,nj->n", g.normal, g.u_q.covariance(n) + g.u_r.covariance(n), g.normal)
        t = along / np.sqrt(var)
        return np.abs(t), 2.0 * ndtr(-np.abs(t)), np.zeros(0)

    return _run_measure(ctx, "welch_m3c2", measure, prepare=with_normals)


class EuclideanParams(BaseModel):
    """Plain Euclidean distance."""

    model_config = ConfigDict(extra="forbid")
    scale: PositiveFloat = Field(1.0, description="Multiply distances by this (e.g. 1000 for mm in a metre twin).")


def _euclidean(ctx: StageContext) -> dict[str, Any]:
    scale = ctx.params.scale

    def measure(g: PairGroup, rng: np.random.Generator) -> tuple[np.ndarray, None, np.ndarray]:
        return np.linalg.norm(g.mu_q - g.mu_r, axis=1) * scale, None, np.zeros(0)

    return _run_measure(ctx, "euclidean", measure)


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in distance measures."""
    common = {"family": "distance", "version": "1.1.0", "requires": ("recent", "reference", "correspondences"),
              "provides": ("scores",)}
    return [
        StageSpec(name="bhattacharyya", params=BhattacharyyaParams, run=_bhattacharyya,
                  description="Bhattacharyya distance for every pair of families (closed forms, quadrature, "
                              "importance sampling; ε_T reported).", **common),
        StageSpec(name="hotelling", params=HotellingParams, run=_hotelling,
                  description="Hotelling's T² with known covariances, p-values from χ²(3) (Gaussians only).",
                  **common),
        StageSpec(name="welch_m3c2", params=WelchParams, run=_welch,
                  description="M3C2-style test on equal means along the local normal (known variances).", **common),
        StageSpec(name="euclidean", params=EuclideanParams, run=_euclidean,
                  description="Plain Euclidean distance to the corresponding position.", **common),
    ]
