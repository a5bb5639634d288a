"""What the ICP registrars share: rigid-transform checks, the schedule parameters, the twin and the recent data as
points (of some LAS classes when asked), coarse-to-fine ICP, and the judged result every registrar returns."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt, field_validator

from gdt_pipeline import Composite, Dataset, Registration, StageContext, StageError
from gdt_pipeline.geometry import sample_surface
from gdt_pipeline.geometry.extent import check_samples, check_scales, expected_samples

from ._classes import class_hint, recent_elements, reference_elements
from ._quality import Fit, Limits, assess, check_covariance, suspicions
from ._schedule import Schedule, schedule_for


def check_rigid(t: np.ndarray, what: str) -> np.ndarray:
    """``t`` as a float 4x4 after checking it is a rigid homogeneous transform (``what`` names it in the error)."""
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (4, 4) or not np.allclose(t[3], [0, 0, 0, 1]):
        raise ValueError(f"{what}: a 4x4 homogeneous transform is needed")
    if not np.allclose(t[:3, :3].T @ t[:3, :3], np.eye(3), atol=1e-6) or np.linalg.det(t[:3, :3]) < 0:
        raise ValueError(f"{what}: the 3x3 part is not a rotation")
    return t


def target_points(reference: Composite, spacing: float, rng: np.random.Generator,
                  elements: list[np.ndarray] | None = None) -> np.ndarray:
    """The twin's current visible geometry as points (only ``elements`` of each item when given)."""
    picks = elements if elements is not None else [np.flatnonzero(it.visible) for it in reference.items]
    pairs = list(zip(reference.items, picks, strict=True))
    count = sum(expected_samples(it.dataset, spacing, e) for it, e in pairs)
    check_samples(count, spacing, "registration", "the twin")
    parts = [sample_surface(it.dataset, spacing, rng, e) for it, e in pairs if len(e)]
    if not parts:
        raise ValueError("the twin has no visible geometry to register to")
    return np.concatenate(parts)


def source_points(recent: list[Dataset], spacing: float, rng: np.random.Generator,
                  elements: list[np.ndarray | None] | None = None) -> np.ndarray:
    """The recent data as points (only ``elements`` of each dataset when given)."""
    picks = elements if elements is not None else [None] * len(recent)
    pairs = list(zip(recent, picks, strict=True))
    check_samples(sum(expected_samples(d, spacing, e) for d, e in pairs), spacing, "registration", "the recent data")
    return np.concatenate([sample_surface(d, spacing, rng, e) for d, e in pairs])


def _diagonal(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


@dataclass(frozen=True)
class Inputs:
    """What a registration fits: the twin's points (target), the recent points (source), the schedule, and what
    is suspect about the choice of points already (a warning each)."""

    tgt: np.ndarray
    src: np.ndarray
    schedule: Schedule
    hints: list[str]


def registration_inputs(ctx: StageContext, method: str) -> Inputs:
    """The twin and the recent data as points (target, source; of ``classes`` only when given) after checking they
    are at the same scale, and the ICP schedule (the params', or scaled to the points' spacing and extent)."""
    recent, reference, p = ctx["recent"], ctx["reference"], ctx.params
    check_scales(recent, reference, method)
    rec_el = recent_elements(recent, p.classes, method)
    ref_el = reference_elements(reference, p.classes, method)
    sets = [d.points if e is None else d.points[e] for d, e in zip(recent, rec_el, strict=True) if d.faces is None]
    sets += [it.dataset.points[e] for it, e in zip(reference.items, ref_el, strict=True) if it.dataset.faces is None]
    schedule = schedule_for(p, sets, _diagonal(np.vstack([d.points for d in recent])), method)
    ctx.report(schedule=schedule.record(), classes=p.classes)
    tgt = target_points(reference, schedule.sample_spacing, ctx.rng, ref_el)
    src = source_points(recent, schedule.sample_spacing, ctx.rng, rec_el)
    hint = class_hint(recent, p.classes)
    return Inputs(tgt, src, schedule, [] if hint is None else [hint])


def to_pcd(points: np.ndarray, origin: np.ndarray) -> Any:
    """An Open3D point cloud of ``points`` relative to ``origin`` (small coordinates for ICP)."""
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64) - origin))


def shifted(t_local: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """A transform computed on coordinates relative to ``origin``, expressed in world coordinates."""
    s, s_inv = np.eye(4), np.eye(4)
    s[:3, 3], s_inv[:3, 3] = -origin, origin
    return s_inv @ t_local @ s


class ScheduleParams(BaseModel):
    """Coarse-to-fine ICP settings shared by the ICP registrars, and when a result is suspect."""

    model_config = ConfigDict(extra="forbid")
    voxels: list[PositiveFloat] | None = Field(
        None, min_length=1, description="Voxel sizes of the coarse-to-fine schedule, twin units (default: 10, 4 and 2 "
                                        "times the data's median point spacing, the coarsest within 5 % of the "
                                        "recent data's bounding-box diagonal).")
    max_distance_factor: PositiveFloat = Field(2.5, description="Correspondence distance = factor x voxel.")
    iterations: PositiveInt = Field(50, description="ICP iterations per level.")
    initial: list[list[float]] | None = Field(None, description="Initial 4x4 transform (default identity).")
    sample_spacing: PositiveFloat | None = Field(None, description="Spacing of samples on meshes (default: the "
                                                                   "finest voxel / 2).")
    classes: list[int] | None = Field(None, min_length=1, description="Fit on the points of these LAS classes only "
                                      "(both epochs, e.g. [2] ground); the transform moves every point.")
    min_fitness: float = Field(0.3, ge=0, le=1, description="Warn below this share of recent points matched.")
    min_overlap: float = Field(0.2, ge=0, le=1, description="Warn below this share of twin points matched.")
    max_residual_share: PositiveFloat = Field(0.25, description="Warn when the residual spread (1.4826 MAD) is over "
                                                                "this share of the correspondence distance.")
    strict: bool = Field(False, description="A suspect registration (the warnings above) is an error instead.")

    @field_validator("initial")
    @classmethod
    def _rigid(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        if v is not None:
            check_rigid(np.asarray(v), "initial")
        return v


def icp_schedule(src: np.ndarray, tgt: np.ndarray, schedule: Schedule, iterations: int, method: str,
                 init: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, float, float, float]:
    """Run ICP level by level; return the local 4x4, fitness, inlier RMSE and the final correspondence distance."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    t = init.copy()
    src_full, tgt_full = to_pcd(src, origin), to_pcd(tgt, origin)
    fitness = rmse = 0.0
    dist = schedule.final_distance
    for voxel in schedule.voxels:
        dist = voxel * schedule.max_distance_factor
        s, g = src_full.voxel_down_sample(voxel), tgt_full.voxel_down_sample(voxel)
        crit = reg.ICPConvergenceCriteria(max_iteration=iterations, relative_fitness=1e-9, relative_rmse=1e-9)
        if method == "gicp":
            res = reg.registration_generalized_icp(s, g, dist, t, reg.TransformationEstimationForGeneralizedICP(),
                                                   crit)
        else:
            g.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
            res = reg.registration_icp(s, g, dist, t, reg.TransformationEstimationPointToPlane(), crit)
        t = np.asarray(res.transformation)
        fitness, rmse = float(res.fitness), float(res.inlier_rmse)
    return t, fitness, rmse, dist


def _judged(ctx: StageContext, fit: Fit, diagonal: float, hints: list[str], method: str) -> list[str]:
    """The fit's covariance checked (an error when NaN or larger than the scene) and its suspicions, with the
    ``hints`` on the points chosen, warned of (or an error under ``strict``)."""
    p = ctx.params
    found = suspicions(fit, Limits(p.min_fitness, p.min_overlap, p.max_residual_share, p.strict))
    check_covariance(fit, diagonal, method, found)
    found += hints
    if found and p.strict:
        raise StageError(f"{method} (strict): the registration is suspect: " + "; ".join(found))
    for text in found:
        ctx.log.warning("%s: suspect registration: %s", method, text)
    return found


def registration_result(ctx: StageContext, inputs: Inputs, fitted: np.ndarray, t_local: np.ndarray,
                        origin: np.ndarray, rmse: float, method: str) -> dict[str, Any]:
    """The registration (world transform, fitness, residual spread, covariance), judged and reported, and the
    recent data moved by it. ``fitted`` are the source points the fit kept (all of ``inputs.src``, or fewer)."""
    src, tgt, schedule = inputs.src, inputs.tgt, inputs.schedule
    fit = assess(fitted - origin, tgt - origin, t_local, schedule.voxels[-1], schedule.final_distance,
                 src - origin)
    if fit.pairs == 0:
        raise ValueError(f"{method}: no correspondences within {fit.distance:g} (twin units); give an `initial` "
                         f"transform, larger voxels, or use the `coarse` registrar")
    warnings = _judged(ctx, fit, max(_diagonal(src), _diagonal(tgt)), inputs.hints, method)
    t_world = shifted(t_local, origin)
    reg = Registration(t_world, fitness=fit.fitness, rmse=rmse, covariance=fit.covariance,
                       method=method, center=origin)
    angle = np.degrees(np.arccos(np.clip((np.trace(t_world[:3, :3]) - 1) / 2, -1, 1)))
    shift_at_center = t_world[:3, :3] @ origin + t_world[:3, 3] - origin  # meaningful where |origin| is large
    sig_rot, sig_t = fit.sigmas()
    ctx.report(fitness=fit.fitness, rmse=rmse, overlap=fit.overlap, residual_sigma=fit.residual_sigma, pairs=fit.pairs,
               rotation_deg=float(angle), shift_at_center=shift_at_center.tolist(), center=origin.tolist(),
               sigma_translation=sig_t.tolist(), sigma_rotation_deg=sig_rot.tolist(), warnings=warnings)
    ctx.log.info("%s: fitness %.3f, overlap %.3f, residual spread %.4g, rotation %.4f deg, shift at the centre %s "
                 "(σ %s)", method, fit.fitness, fit.overlap, fit.residual_sigma, angle,
                 np.round(shift_at_center, 6).tolist(), np.round(sig_t, 6).tolist())
    return {"recent": [d.transformed(t_world) for d in ctx["recent"]], "registration": reg}
