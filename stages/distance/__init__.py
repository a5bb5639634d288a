"""Distance measures (paper Sec. 4.2.1), one score per recent element against its correspondence:

- ``bhattacharyya``: BD = −ln ∫√(p₁p₂) for every pair of families (closed forms where they exist, numerical
  integration with a reported tolerance ε_T otherwise; see ``measures``);
- ``hotelling``: T² = dᵀ(Σ₁+Σ₂)⁻¹d with p-values from χ²(3), for Gaussians only (the test holds only for normals);
- ``welch_m3c2``: the M3C2-style test on equal means along the local normal, with known variances
  (t = nᵀd / √(nᵀΣ₁n + nᵀΣ₂n), two-sided p-value), as a baseline inside the pipeline;
- ``euclidean``: the plain distance, for comparison.

Each is a pair function run through the public ``gdt_pipeline.measures`` (pairing of correspondences, lowest score
per element, and a ``simulate(rng, n)`` on every ``Scores`` that scores n unchanged pairs drawn from the actual
uncertainty models, which the ``calibrated_threshold`` stage uses); the Bhattacharyya maths is in ``.measures``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt
from scipy.special import ndtr
from scipy.stats import chi2

from gdt_pipeline import GaussianUncertainty, StageContext, StageSpec, hookimpl
from gdt_pipeline.geometry import estimate_normals, quad_inv3
from gdt_pipeline.measures import (
    DISTANCE_REQUIRES,
    MeasureResult,
    PairGroup,
    PairMeasure,
    attach_null_simulators,
    distance_stage,
    euclidean,
    run_pair_measure,
)

from .bhattacharyya_maths import bd_gauss_gauss, bhattacharyya

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


def _bd_measure(p: BhattacharyyaParams, methods: set[str] | None = None, paths: dict[str, int] | None = None
                ) -> PairMeasure:
    """The Bhattacharyya pair function for these params, noting the methods and Gaussian–box paths it used."""
    methods = set() if methods is None else methods
    paths = {} if paths is None else paths

    def measure(g: PairGroup, rng: np.random.Generator) -> tuple[np.ndarray, None, np.ndarray]:
        u_q, u_r = g.u_q, g.u_r
        if p.non_gaussian == "moment_match":
            n = len(g.idx)
            u_q, u_r = u_q.moment_matched(n), u_r.moment_matched(n)
        bd, err, method = bhattacharyya(g.mu_q, u_q, g.mu_r, u_r, rng=rng, eps=p.epsilon, samples=p.samples,
                                        paths=paths)
        methods.add(method)
        return bd, None, err

    return measure


def _bhattacharyya(ctx: StageContext) -> dict[str, Any]:
    methods: set[str] = set()
    paths: dict[str, int] = {}
    out = run_pair_measure(ctx, "bhattacharyya", _bd_measure(ctx.params, methods, paths), tolerance=ctx.params.epsilon)
    total = sum(paths.values())
    ctx.report(methods=sorted(methods), gaussian_box_pairs=total,
               path_shares={k: round(v / total, 6) for k, v in sorted(paths.items())} if total else {})
    return out


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
    return t2, chi2.sf(t2, 3), np.zeros(0)


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

    return run_pair_measure(ctx, "welch_m3c2", measure, prepare=with_normals)


class EuclideanParams(BaseModel):
    """Plain Euclidean distance."""

    model_config = ConfigDict(extra="forbid")
    scale: PositiveFloat = Field(1.0, description="Multiply distances by this (e.g. 1000 for mm in a metre twin).")


def _euclidean(g: PairGroup, rng: np.random.Generator, params: EuclideanParams) -> MeasureResult:
    return euclidean(g, rng, params.scale)


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in distance measures."""
    version = "1.1.0"
    common = {"family": "distance", "version": version, "requires": DISTANCE_REQUIRES, "provides": ("scores",)}
    return [
        StageSpec(name="bhattacharyya", params=BhattacharyyaParams, run=_bhattacharyya,
                  description="Bhattacharyya distance for every pair of families (closed forms, quadrature, "
                              "importance sampling; ε_T reported).", tiling="tile",
                  finish=lambda ctx: attach_null_simulators(ctx, _bd_measure(ctx.params)), **common),
        distance_stage(name="hotelling", measure=hotelling, params=HotellingParams, version=version,
                       description="Hotelling's T² with known covariances, p-values from χ²(3) (Gaussians only)."),
        StageSpec(name="welch_m3c2", params=WelchParams, run=_welch,
                  description="M3C2-style test on equal means along the local normal (known variances).", **common),
        distance_stage(name="euclidean", measure=_euclidean, params=EuclideanParams, version=version,
                       description="Plain Euclidean distance to the corresponding position."),
    ]
