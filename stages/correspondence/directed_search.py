"""The paper's uncertainty-directed correspondences (Sec. 4.2.2) as stages: ``point_to_point``, ``point_to_mesh``,
``mesh_to_point`` and ``mesh_to_mesh``, each for its kinds of data, and ``auto``, which picks the case per recent
dataset and per reference item from their kinds (the geometry of the four cases is ``directed``; the neighbourhood
expectation a recent point may be judged by is ``expectation``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt

from gdt_pipeline import Dataset, GaussianUncertainty, StageContext, StageSpec, family_stage
from gdt_pipeline.geometry.extent import check_scales
from gdt_pipeline.types.arrays import by_pieces
from gdt_pipeline.types.region99 import reach_factor

from .directed import (
    ReferenceMeshes,
    ReferencePoints,
    default_density,
    point_to_mesh,
    point_to_point,
    query_samples,
    to_correspondences,
)
from .expectation import expectations


class DirectedParams(BaseModel):
    """Parameters of the uncertainty-directed correspondence search."""

    model_config = ConfigDict(extra="forbid")
    probability: float = Field(0.99, gt=0.5, lt=1.0, description="Probability of the ellipsoid holding the "
                                                                  "point-to-point neighbours (combined uncertainty).")
    search_sigmas: PositiveFloat = Field(4.0, description="Reach of rays and closest points, in standard deviations "
                                                          "of the largest combined uncertainty axis.")
    max_components: PositiveInt = Field(16, description="Neighbours kept per point-to-point mixture (closest "
                                                        "in Mahalanobis distance, out of 4x as many "
                                                        "Euclidean-nearest per variance tier).")
    sample_density: PositiveFloat | None = Field(None, description="Samples per unit² on recent facets (default: "
                                                                   "about four on an average facet).")
    max_samples_per_facet: PositiveInt = Field(64, description="Cap of samples on one facet.")
    surface_sampling: bool = Field(True, description="Reference points also carry where the surface lies between "
                                                     "them: (half their spacing)² in their tangent plane, so a sparse "
                                                     "precise scan matches a later one sampled elsewhere.")
    expectation: Literal["auto", "point", "neighbourhood"] = Field(
        "auto", description="What a recent point is judged by: its own position and covariance (point: the "
                            "per-point test), or the expectation of the twin's surface it lies on, pooled over its "
                            "neighbours (neighbourhood; docs/distances.md). auto: pooled where a point cloud with "
                            "Gaussian covariances meets the twin's meshes and has neighbours within its 99 % "
                            "region, per point elsewhere; neighbourhood warns where it cannot pool.")
    pooling_neighbours: PositiveInt = Field(256, ge=8, description="Nearest neighbours a point's expectation "
                                                                   "draws on (in four quadrants, each pooled at 2, "
                                                                   "4, 8, … of its own).")
    pooling_radius: PositiveFloat | None = Field(
        None, description="Metres: neighbours' anchors on the twin's surface lie within this of the point's own. "
                          "Default: the radius of the point's own 99 % region (wide for noisy points, narrow for "
                          "precise ones).")
    pooling_gamma: PositiveFloat = Field(1.5, description="Half width, in σ, of the confidence intervals that "
                                                          "choose each point's scale (smaller: smaller scales).")


def _directed(ctx: StageContext, name: str, query_kind: str | None, use_points: bool, use_meshes: bool
              ) -> dict[str, Any]:
    p = ctx.params
    reference = ctx["reference"]
    check_scales(ctx["recent"], reference, name)
    ref_pts = ReferencePoints(reference, p.surface_sampling) if use_points else None
    ref_mesh = ReferenceMeshes(reference) if use_meshes else None
    if (ref_pts is None or ref_pts.empty) and (ref_mesh is None or ref_mesh.empty):
        if ctx.tile is not None:  # a tile past the twin's data (a strip an earlier survey never reached)
            empty = [to_correspondences(qi, ds.n_elements, [], name) for qi, ds in enumerate(ctx["recent"])]
            return {"correspondences": [c if ds.faces is not None else dataclasses.replace(c, query_position=None)
                                        for c, ds in zip(empty, ctx["recent"], strict=True)]}
        wanted = " or ".join(k for k, u in (("points", use_points), ("meshes", use_meshes)) if u)
        raise ValueError(f"{name}: the twin holds no visible {wanted} to match against")
    q99 = _chi2_3(p.probability)
    extra_var = 0.0
    if ref_mesh is not None and not ref_mesh.empty:
        extra_var = max(float(np.linalg.eigvalsh(np.asarray(reference.items[i].dataset.element_covariance())
                                                 [vis]).max()) for i, vis in ref_mesh.items)
    expected = expectations(ctx, ref_mesh) if p.expectation != "point" else {}
    out = []
    for qi, ds in enumerate(ctx["recent"]):
        if query_kind is not None and ds.kind != query_kind:
            other = {"points": "point", "mesh": "mesh"}[ds.kind]
            raise ValueError(f"{name} matches {query_kind} data, but {ds.name!r} is a {ds.kind}; use "
                             f"{other}_to_{'point' if use_points else 'mesh'} or auto")
        if ds.uncertainty is None:
            raise ValueError(f"recent dataset {ds.name!r} has no uncertainty: add an uncertainty stage before {name}")
        # the density from the whole epoch (a tile holds some facets only); facets sampled by their own hash
        density = p.sample_density or ctx.survey.get("facet_density", {}).get(ds.name)
        qpos, element = query_samples(ds, _sample_seed(ctx), density, p.max_samples_per_facet)
        if ds.name in expected:
            qpos, qcov = expected[ds.name].position[element], expected[ds.name].covariance[element]
        else:
            qcov = np.asarray(ds.uncertainty.covariance(ds.n_elements))[element]
        parts = []
        if ref_pts is not None and not ref_pts.empty:
            parts.append(point_to_point(qpos, qcov, ref_pts, q99 * reach_factor(ds.uncertainty) ** 2,
                                            p.max_components, element))
        if ref_mesh is not None and not ref_mesh.empty:
            # a heavy-tailed (Student t) scan reaches as much farther as its 99 % region does
            parts.append(point_to_mesh(qpos, qcov, ref_mesh, p.search_sigmas * reach_factor(ds.uncertainty),
                                       extra_var, element))
        corr = to_correspondences(qi, ds.n_elements, parts, name)
        if ds.name in expected:
            # a heavy-tailed (Student t) query keeps its ν: exact where a point kept its own value, conservative
            # for a pooled mean (lighter-tailed than its points)
            corr = dataclasses.replace(corr, query_uncertainty=GaussianUncertainty(
                expected[ds.name].covariance[corr.element], dof=getattr(ds.uncertainty, "dof", None)))
        elif ds.faces is None:  # the queries are the points themselves: no copy of them per candidate (24 B each)
            corr = dataclasses.replace(corr, query_position=None)
        matched = int(corr.element_found().sum())
        ctx.log.info("%s: %d of %d elements have candidates (%d candidates from %d query points)", ds.name, matched,
                     ds.n_elements, len(corr.ref_item), len(qpos))
        ctx.report(**{ds.name: {"elements": ds.n_elements, "matched": matched, "candidates": len(corr.ref_item),
                                "query_points": len(qpos)}})
        out.append(corr)
    return {"correspondences": out}


def _sample_seed(ctx: StageContext) -> int:
    """The seed of facet samples: the workflow's, the epoch's and the stage's place (the same in every tile)."""
    return int(np.random.SeedSequence(ctx.epoch.seed, spawn_key=(ctx.epoch.index, 0xFACE)).generate_state(1)[0])


def _directed_survey(params: DirectedParams, slots: Mapping[str, Any]) -> dict[str, Any]:
    """The default sample density of each recent mesh, from all its facets (a tile holds some only)."""
    return {"facet_density": {ds.name: default_density(ds) for ds in slots["recent"]
                              if ds.faces is not None and len(ds.faces)}}


def element_variances(u: Any, n: int) -> np.ndarray:
    """Per element a bound on its largest variance: its covariance's trace (cheap, and ≥ the top eigenvalue)."""
    if n == 0:
        return np.zeros(0)
    # a piece at a time over rows kept in a scratch file: the whole file's pages stayed resident (72 B a point)
    trace = by_pieces(u.covariance(u.rows), lambda rows: np.einsum("nii->n", np.asarray(rows)))
    return np.broadcast_to(trace, (n,)) if len(trace) == 1 else trace


def _largest_variance(u: Any) -> float:
    """A bound on the largest variance of a model's rows: the largest trace."""
    trace = element_variances(u, u.rows)
    return float(trace.max()) if len(trace) else 0.0


def _facet_sizes(ds: Dataset) -> np.ndarray:
    """Per recent element, how far its surface samples can lie from its position: a facet's farthest corner (0 for
    a point)."""
    if ds.faces is None or not len(ds.faces):
        return np.zeros(ds.n_elements)
    return np.linalg.norm(ds.points[ds.faces] - ds.element_positions()[:, None], axis=2).max(axis=1)


def _directed_reach(params: DirectedParams, slots: Mapping[str, Any]) -> list[np.ndarray]:
    """Per recent element, how far from it a candidate can lie: the ray and closest-point reach against meshes, the
    99 % ellipsoid against points (with the surface-sampling spread), plus a facet's size for samples on recent
    facets. A pooled point's reach is its neighbours' too: the runner takes a tile's largest over every element
    within the widest reach of its core, so its own variance stands for theirs (``runner.halos``)."""
    recent, reference = slots["recent"], slots["reference"]
    if any(ds.uncertainty is None for ds in recent):
        raise ValueError("the search reach needs the recent data's uncertainty: add an uncertainty stage before")
    meshes = [it for it in reference.items if it.dataset.faces is not None and it.visible.any()]
    var_mesh = max((_largest_variance(it.dataset.uncertainty) for it in meshes), default=0.0)
    var_pts = (ReferencePoints(reference, params.surface_sampling).max_var
               if any(it.dataset.faces is None and it.visible.any() for it in reference.items) else None)
    out = []
    for ds in recent:
        var_q = element_variances(ds.uncertainty, ds.n_elements) * reach_factor(ds.uncertainty) ** 2
        reach = params.search_sigmas * np.sqrt(var_q + var_mesh) if meshes else np.zeros(ds.n_elements)
        if var_pts is not None:
            reach = np.maximum(reach, np.sqrt(_chi2_3(params.probability) * (var_q + var_pts)))
        if params.expectation != "point" and meshes:
            # a pooled point's neighbours: anchors within the pooling radius, each point within the search reach of
            # its anchor, twice over (the second pass anchors by the first one's neighbours)
            slack = params.search_sigmas * np.sqrt(var_q)
            widest = params.pooling_radius or np.sqrt(_chi2_3(0.99) * var_q)
            reach = np.maximum(reach, 2 * widest + 4 * slack)
        out.append(np.asarray(reach + _facet_sizes(ds), dtype=np.float64))
    return out


def _chi2_3(probability: float) -> float:
    """The χ² quantile of three degrees of freedom (scipy.stats imported here: it takes a third of a second, and
    commands that only load the stages need none of it)."""
    from scipy.stats import chi2

    return float(chi2.ppf(probability, 3))


def _stage(name: str, query_kind: str | None, points: bool, meshes: bool, description: str) -> StageSpec:
    return family_stage("correspondence", name=name, version="1.1.0", params=DirectedParams,
                        run=lambda ctx: _directed(ctx, name, query_kind, points, meshes), description=description,
                        tiling="tile", reach=_directed_reach, survey=_directed_survey)


POINT_TO_POINT = _stage("point_to_point", "points", True, False,
                        "Reference points inside the query's 99 % ellipsoid, merged into a mixture.")
POINT_TO_MESH = _stage("point_to_mesh", "points", False, True,
                       "Ray along the largest uncertainty axis (both senses) and closest point; lower score wins.")
MESH_TO_POINT = _stage("mesh_to_point", "mesh", True, False,
                       "Seeded samples on each facet, each point-to-point; the facet keeps its lowest score.")
MESH_TO_MESH = _stage("mesh_to_mesh", "mesh", False, True,
                      "Seeded samples on each facet, each point-to-mesh; the facet keeps its lowest score.")
AUTO = _stage("auto", None, True, True, "The case from the kinds of the recent data and of each reference item.")
