"""``coarse``: FPFH features + RANSAC (Open3D) for data that starts far off, refined by ICP."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import Field, PositiveFloat, PositiveInt

from gdt_pipeline import StageContext, family_stage

from ._icp import ScheduleParams, icp_schedule, registration_inputs, registration_result, to_pcd


class CoarseParams(ScheduleParams):
    """FPFH + RANSAC global alignment, refined by ICP."""

    feature_voxel: PositiveFloat | None = Field(None, description="Voxel for the FPFH features and RANSAC, twin "
                                                                  "units (default: the schedule's coarsest).")
    ransac_iterations: PositiveInt = Field(100_000, description="RANSAC iterations.")
    confidence: float = Field(0.999, gt=0, lt=1, description="RANSAC confidence.")
    refine: Literal["point_to_plane", "gicp"] = "point_to_plane"


def coarse(ctx: StageContext) -> dict[str, Any]:
    """FPFH features and RANSAC for a global alignment, refined by ICP."""
    import open3d as o3d

    p = ctx.params
    reg = o3d.pipelines.registration
    inputs = registration_inputs(ctx, "coarse")
    tgt, src, schedule = inputs.tgt, inputs.src, inputs.schedule
    origin = tgt.mean(axis=0)
    v = p.feature_voxel or schedule.voxels[0]
    feats = []
    for pts in (src, tgt):
        pcd = to_pcd(pts, origin).voxel_down_sample(v)
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
    t_local, _, rmse, _ = icp_schedule(src, tgt, schedule, p.iterations, p.refine, np.asarray(res.transformation),
                                       origin)
    return registration_result(ctx, inputs, src, t_local, origin, rmse, f"coarse+{p.refine}")


SPEC = family_stage("registrar", name="coarse", version="2.0.0", params=CoarseParams, run=coarse,
                    description="FPFH + RANSAC global alignment refined by ICP, for data that starts far off.")
