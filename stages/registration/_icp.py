"""What the ICP registrars share: rigid-transform checks, the schedule parameters, the twin and the recent data as
points, coarse-to-fine ICP, the transform's covariance, and the result every registrar returns."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt, field_validator

from gdt_pipeline import Composite, Dataset, Registration, StageContext
from gdt_pipeline.geometry import sample_surface
from gdt_pipeline.geometry.extent import check_samples, check_scales, expected_samples


def check_rigid(t: np.ndarray, what: str) -> np.ndarray:
    """``t`` as a float 4x4 after checking it is a rigid homogeneous transform (``what`` names it in the error)."""
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (4, 4) or not np.allclose(t[3], [0, 0, 0, 1]):
        raise ValueError(f"{what}: a 4x4 homogeneous transform is needed")
    if not np.allclose(t[:3, :3].T @ t[:3, :3], np.eye(3), atol=1e-6) or np.linalg.det(t[:3, :3]) < 0:
        raise ValueError(f"{what}: the 3x3 part is not a rotation")
    return t


def target_points(reference: Composite, spacing: float, rng: np.random.Generator) -> np.ndarray:
    """The twin's current visible geometry as points."""
    count = sum(expected_samples(it.dataset, spacing, np.flatnonzero(it.visible)) for it in reference.items)
    check_samples(count, spacing, "registration", "the twin")
    parts = [sample_surface(it.dataset, spacing, rng, np.flatnonzero(it.visible))
             for it in reference.items if it.visible.any()]
    if not parts:
        raise ValueError("the twin has no visible geometry to register to")
    return np.concatenate(parts)


def source_points(recent: list[Dataset], spacing: float, rng: np.random.Generator) -> np.ndarray:
    """The recent data as points."""
    check_samples(sum(expected_samples(d, spacing) for d in recent), spacing, "registration", "the recent data")
    return np.concatenate([sample_surface(d, spacing, rng) for d in recent])


def registration_inputs(ctx: StageContext, spacing: float, method: str) -> tuple[np.ndarray, np.ndarray]:
    """The twin and the recent data as points (target, source), after checking they are at the same scale."""
    check_scales(ctx["recent"], ctx["reference"], method)
    return target_points(ctx["reference"], spacing, ctx.rng), source_points(ctx["recent"], spacing, ctx.rng)


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
    """Coarse-to-fine ICP settings shared by the ICP registrars."""

    model_config = ConfigDict(extra="forbid")
    voxels: list[PositiveFloat] = Field([0.05, 0.02, 0.01], min_length=1,
                                        description="Voxel sizes of the coarse-to-fine schedule, twin units.")
    max_distance_factor: PositiveFloat = Field(2.5, description="Correspondence distance = factor x voxel.")
    iterations: PositiveInt = Field(50, description="ICP iterations per level.")
    initial: list[list[float]] | None = Field(None, description="Initial 4x4 transform (default identity).")
    sample_spacing: PositiveFloat | None = Field(None, description="Spacing of samples on meshes (default: the "
                                                                   "finest voxel / 2).")

    @field_validator("initial")
    @classmethod
    def _rigid(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        if v is not None:
            check_rigid(np.asarray(v), "initial")
        return v


def icp_schedule(src: np.ndarray, tgt: np.ndarray, params: ScheduleParams, method: str, init: np.ndarray,
                 origin: np.ndarray) -> tuple[np.ndarray, float, float, float]:
    """Run ICP level by level; return the local 4x4, fitness, inlier RMSE and the final correspondence distance."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    t = init.copy()
    src_full, tgt_full = to_pcd(src, origin), to_pcd(tgt, origin)
    fitness = rmse = 0.0
    dist = params.voxels[-1] * params.max_distance_factor
    for voxel in params.voxels:
        dist = voxel * params.max_distance_factor
        s, g = src_full.voxel_down_sample(voxel), tgt_full.voxel_down_sample(voxel)
        crit = reg.ICPConvergenceCriteria(max_iteration=params.iterations, relative_fitness=1e-9, relative_rmse=1e-9)
        if method == "gicp":
            res = reg.registration_generalized_icp(s, g, dist, t, reg.TransformationEstimationForGeneralizedICP(),
                                                   crit)
        else:
            g.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
            res = reg.registration_icp(s, g, dist, t, reg.TransformationEstimationPointToPlane(), crit)
        t = np.asarray(res.transformation)
        fitness, rmse = float(res.fitness), float(res.inlier_rmse)
    return t, fitness, rmse, dist


def transform_covariance(src: np.ndarray, tgt: np.ndarray, t_local: np.ndarray, origin: np.ndarray, dist: float,
                         rmse: float) -> np.ndarray:
    """6x6 covariance (ω, t) about ``origin``: σ² · info⁻¹, with Open3D's information matrix and σ² = RMSE²/3."""
    import open3d as o3d

    info = np.asarray(o3d.pipelines.registration.get_information_matrix_from_point_clouds(
        to_pcd(src, origin), to_pcd(tgt, origin), dist, t_local))
    sigma2 = max(rmse, 1e-12) ** 2 / 3.0
    try:
        return sigma2 * np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return sigma2 * np.linalg.pinv(info)


def registration_result(ctx: StageContext, src: np.ndarray, tgt: np.ndarray, t_local: np.ndarray,
                        origin: np.ndarray, fitness: float, rmse: float, dist: float, method: str) -> dict[str, Any]:
    """The registration (world transform, fitness, RMSE, covariance), reported, and the recent data moved by it."""
    if fitness == 0.0:
        raise ValueError(f"{method}: no correspondences within {dist:g} (twin units); give an `initial` transform, "
                         f"larger voxels, or use the `coarse` registrar")
    cov = transform_covariance(src, tgt, t_local, origin, dist, rmse)
    t_world = shifted(t_local, origin)
    reg = Registration(t_world, fitness=fitness, rmse=rmse, covariance=cov, method=method, center=origin)
    angle = np.degrees(np.arccos(np.clip((np.trace(t_world[:3, :3]) - 1) / 2, -1, 1)))
    shift_at_center = t_world[:3, :3] @ origin + t_world[:3, 3] - origin  # meaningful where |origin| is large
    ctx.report(fitness=fitness, rmse=rmse, rotation_deg=float(angle), shift_at_center=shift_at_center.tolist(),
               center=origin.tolist(),
               sigma_translation=np.sqrt(np.diag(cov)[3:]).tolist(),
               sigma_rotation_deg=np.degrees(np.sqrt(np.diag(cov)[:3])).tolist())
    ctx.log.info("%s: fitness %.3f, rmse %.4g, rotation %.4f deg, shift at the centre %s", method, fitness, rmse,
                 angle, np.round(shift_at_center, 6).tolist())
    return {"recent": [d.transformed(t_world) for d in ctx["recent"]], "registration": reg}
