"""Registrars: co-register each epoch's recent data to the twin (paper Fig. 3; the paper used Generalized-ICP).

- ``gicp``: Open3D's Generalized-ICP, coarse to fine over a voxel schedule, from an optional initial transform;
- ``point_to_plane``: Open3D's point-to-plane ICP, same schedule;
- ``coarse``: FPFH features + RANSAC (Open3D) for data that starts far off, refined by point-to-plane ICP;
- ``stable_areas``: ICP restricted to areas known to be stable: a user box, and iterative trimming of the points
  whose residuals say they lie on changed geometry (new objects bias a plain ICP);
- ``identity`` and ``given`` (a 4x4 from the workflow or a file), for pre-registered data.

The target is the twin's current visible geometry: points as they are, meshes sampled (area-weighted, seeded).
Every registrar outputs the transform, fitness, RMSE and a 6x6 covariance (ω, t) from Open3D's information matrix
scaled by the residual variance, expressed about the target's centre; the recent datasets come out transformed (their
covariances and box axes rotated with them).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt, field_validator
from scipy.spatial import cKDTree

from gdt_pipeline import Composite, Dataset, Registration, StageContext, StageSpec, hookimpl
from gdt_pipeline.geometry import sample_surface

VERSION = "1.0.0"


class IdentityParams(BaseModel):
    """``identity`` has no parameters."""

    model_config = ConfigDict(extra="forbid")


def _identity(ctx: StageContext) -> dict[str, Any]:
    return {"recent": list(ctx["recent"]), "registration": Registration(np.eye(4), method="identity")}


def _check_rigid(t: np.ndarray, what: str) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (4, 4) or not np.allclose(t[3], [0, 0, 0, 1]):
        raise ValueError(f"{what}: a 4x4 homogeneous transform is needed")
    if not np.allclose(t[:3, :3].T @ t[:3, :3], np.eye(3), atol=1e-6) or np.linalg.det(t[:3, :3]) < 0:
        raise ValueError(f"{what}: the 3x3 part is not a rotation")
    return t


class GivenParams(BaseModel):
    """A known transform, inline or from a file."""

    model_config = ConfigDict(extra="forbid")
    transform: list[list[float]] | None = Field(None, description="4x4 row-major matrix.")
    file: str | None = Field(None, description="File with the 4x4 (whitespace text, .npy or .json), relative to "
                                               "the workflow.")

    @field_validator("transform")
    @classmethod
    def _rigid(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        if v is not None:
            _check_rigid(np.asarray(v), "transform")
        return v


def _load_matrix(path: Path) -> np.ndarray:
    if path.suffix == ".npy":
        return np.load(path)
    if path.suffix == ".json":
        return np.asarray(json.loads(path.read_text()), dtype=np.float64)
    return np.loadtxt(path)


def _given(ctx: StageContext) -> dict[str, Any]:
    p = ctx.params
    if (p.transform is None) == (p.file is None):
        raise ValueError("given: set exactly one of `transform` or `file`")
    if p.file is not None:
        path = (ctx.epoch.workflow_dir / p.file).resolve()
        if not path.is_file():
            raise ValueError(f"given: transform file not found: {path}")
        t = _check_rigid(_load_matrix(path), str(path))
    else:
        t = np.asarray(p.transform, dtype=np.float64)
    return {"recent": [d.transformed(t) for d in ctx["recent"]], "registration": Registration(t, method="given")}


# ---------------------------------------------------------------------------------------------------------------------
# Geometry for ICP


def target_points(reference: Composite, spacing: float, rng: np.random.Generator) -> np.ndarray:
    """The twin's current visible geometry as points."""
    parts = [sample_surface(it.dataset, spacing, rng, np.flatnonzero(it.visible))
             for it in reference.items if it.visible.any()]
    if not parts:
        raise ValueError("the twin has no visible geometry to register to")
    return np.concatenate(parts)


def source_points(recent: list[Dataset], spacing: float, rng: np.random.Generator) -> np.ndarray:
    """The recent data as points."""
    return np.concatenate([sample_surface(d, spacing, rng) for d in recent])


def _pcd(points: np.ndarray, origin: np.ndarray) -> Any:
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64) - origin))


def _shift(t_local: np.ndarray, origin: np.ndarray) -> np.ndarray:
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
            _check_rigid(np.asarray(v), "initial")
        return v


def icp_schedule(src: np.ndarray, tgt: np.ndarray, params: ScheduleParams, method: str, init: np.ndarray,
                 origin: np.ndarray) -> tuple[np.ndarray, float, float, float]:
    """Run ICP level by level; return the local 4x4, fitness, inlier RMSE and the final correspondence distance."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    t = init.copy()
    src_full, tgt_full = _pcd(src, origin), _pcd(tgt, origin)
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
        _pcd(src, origin), _pcd(tgt, origin), dist, t_local))
    sigma2 = max(rmse, 1e-12) ** 2 / 3.0
    try:
        return sigma2 * np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return sigma2 * np.linalg.pinv(info)


def _icp(ctx: StageContext, method: str) -> dict[str, Any]:
    p = ctx.params
    spacing = p.sample_spacing or p.voxels[-1] / 2
    tgt = target_points(ctx["reference"], spacing, ctx.rng)
    src = source_points(ctx["recent"], spacing, ctx.rng)
    origin = tgt.mean(axis=0)
    init_world = np.eye(4) if p.initial is None else np.asarray(p.initial, dtype=np.float64)
    init_local = _shift(init_world, -origin)
    t_local, fitness, rmse, dist = icp_schedule(src, tgt, p, method, init_local, origin)
    return _result(ctx, src, tgt, t_local, origin, fitness, rmse, dist, method)


def _result(ctx: StageContext, src: np.ndarray, tgt: np.ndarray, t_local: np.ndarray, origin: np.ndarray,
            fitness: float, rmse: float, dist: float, method: str) -> dict[str, Any]:
    if fitness == 0.0:
        raise ValueError(f"{method}: no correspondences within {dist:g} (twin units); give an `initial` transform, "
                         f"larger voxels, or use the `coarse` registrar")
    cov = transform_covariance(src, tgt, t_local, origin, dist, rmse)
    t_world = _shift(t_local, origin)
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


class GicpParams(ScheduleParams):
    """Generalized-ICP, coarse to fine."""


class PointToPlaneParams(ScheduleParams):
    """Point-to-plane ICP, coarse to fine."""


def _gicp(ctx: StageContext) -> dict[str, Any]:
    return _icp(ctx, "gicp")


def _point_to_plane(ctx: StageContext) -> dict[str, Any]:
    return _icp(ctx, "point_to_plane")


class CoarseParams(ScheduleParams):
    """FPFH + RANSAC global alignment, refined by ICP."""

    feature_voxel: PositiveFloat = Field(0.05, description="Voxel for the FPFH features and RANSAC, twin units.")
    ransac_iterations: PositiveInt = Field(100_000, description="RANSAC iterations.")
    confidence: float = Field(0.999, gt=0, lt=1, description="RANSAC confidence.")
    refine: Literal["point_to_plane", "gicp"] = "point_to_plane"


def _coarse(ctx: StageContext) -> dict[str, Any]:
    import open3d as o3d

    p = ctx.params
    reg = o3d.pipelines.registration
    spacing = p.sample_spacing or p.voxels[-1] / 2
    tgt = target_points(ctx["reference"], spacing, ctx.rng)
    src = source_points(ctx["recent"], spacing, ctx.rng)
    origin = tgt.mean(axis=0)
    v = p.feature_voxel
    feats = []
    for pts in (src, tgt):
        pcd = _pcd(pts, origin).voxel_down_sample(v)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
        fpfh = reg.compute_fpfh_feature(pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * v, max_nn=100))
        feats.append((pcd, fpfh))
    o3d.utility.random.seed(int(ctx.seed))  # RANSAC draws from Open3D's own generator: seed it from the workflow
    res = reg.registration_ransac_based_on_feature_matching(
        feats[0][0], feats[1][0], feats[0][1], feats[1][1], True, 1.5 * v,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * v)],
        reg.RANSACConvergenceCriteria(p.ransac_iterations, p.confidence))
    ctx.report(ransac_fitness=float(res.fitness), ransac_rmse=float(res.inlier_rmse))
    t_local, fitness, rmse, dist = icp_schedule(src, tgt, p, p.refine, np.asarray(res.transformation), origin)
    return _result(ctx, src, tgt, t_local, origin, fitness, rmse, dist, f"coarse+{p.refine}")


class StableAreasParams(ScheduleParams):
    """ICP on stable areas only: inside a box, and trimmed of points whose residuals mark them as changed."""

    method: Literal["gicp", "point_to_plane"] = "gicp"
    box: list[list[float]] | None = Field(None, description="[[xmin, ymin, zmin], [xmax, ymax, zmax]]: only recent "
                                                            "points inside it are used.")
    trim_rounds: int = Field(3, ge=0, le=20, description="Rounds of dropping points with large residuals.")
    trim_k: PositiveFloat = Field(3.0, description="Drop residuals above k robust sigmas (1.4826 MAD).")


def _stable_areas(ctx: StageContext) -> dict[str, Any]:
    p = ctx.params
    spacing = p.sample_spacing or p.voxels[-1] / 2
    tgt = target_points(ctx["reference"], spacing, ctx.rng)
    src = source_points(ctx["recent"], spacing, ctx.rng)
    if p.box is not None:
        lo, hi = np.asarray(p.box[0]), np.asarray(p.box[1])
        src = src[np.all((src >= lo) & (src <= hi), axis=1)]
        if len(src) < 10:
            raise ValueError(f"stable_areas: only {len(src)} recent points inside the box {p.box}")
    origin = tgt.mean(axis=0)
    t_local = _shift(np.eye(4) if p.initial is None else np.asarray(p.initial), -origin)
    tree = cKDTree(tgt - origin)
    kept = src
    fitness = rmse = 0.0
    dist = p.voxels[-1] * p.max_distance_factor
    for round_ in range(p.trim_rounds + 1):
        t_local, fitness, rmse, dist = icp_schedule(kept, tgt, p, p.method, t_local, origin)
        if round_ == p.trim_rounds:
            break
        moved = (src - origin) @ t_local[:3, :3].T + t_local[:3, 3]
        d, _ = tree.query(moved)
        med = np.median(d)
        robust = 1.4826 * np.median(np.abs(d - med))
        keep = d <= med + p.trim_k * max(robust, 1e-12)
        ctx.log.info("stable_areas round %d: keeping %d of %d points (residual cut %.4g)", round_, int(keep.sum()),
                     len(src), med + p.trim_k * robust)
        kept = src[keep]
    ctx.report(stable_points=len(kept), all_points=len(src))
    return _result(ctx, kept, tgt, t_local, origin, fitness, rmse, dist, f"stable_areas+{p.method}")


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in registrars."""
    common = {"family": "registrar", "version": VERSION, "requires": ("recent", "reference"),
              "provides": ("recent", "registration")}
    return [
        StageSpec(name="identity", family="registrar", version=VERSION, params=IdentityParams, run=_identity,
                  requires=("recent",), provides=("recent", "registration"),
                  description="Keep the recent data where it is (pre-registered input)."),
        StageSpec(name="given", family="registrar", version=VERSION, params=GivenParams, run=_given,
                  requires=("recent",), provides=("recent", "registration"),
                  description="Apply a known 4x4 transform (inline or from a file)."),
        StageSpec(name="gicp", params=GicpParams, run=_gicp,
                  description="Generalized-ICP to the twin's geometry, coarse to fine (Open3D).", **common),
        StageSpec(name="point_to_plane", params=PointToPlaneParams, run=_point_to_plane,
                  description="Point-to-plane ICP to the twin's geometry, coarse to fine (Open3D).", **common),
        StageSpec(name="coarse", params=CoarseParams, run=_coarse,
                  description="FPFH + RANSAC global alignment refined by ICP, for data that starts far off.",
                  **common),
        StageSpec(name="stable_areas", params=StableAreasParams, run=_stable_areas,
                  description="ICP on stable areas only (box, and trimming of changed points).", **common),
    ]
