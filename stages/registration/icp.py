"""``gicp`` and ``point_to_plane``: Open3D's Generalized-ICP or point-to-plane ICP, coarse to fine over a voxel
schedule, from an optional initial transform."""

from __future__ import annotations

from typing import Any

import numpy as np

from gdt_pipeline import StageContext, family_stage

from ._icp import ScheduleParams, icp_schedule, registration_inputs, registration_result, shifted


def icp(ctx: StageContext, method: str) -> dict[str, Any]:
    """ICP of ``method`` (gicp or point_to_plane) from the initial transform, coarse to fine."""
    p = ctx.params
    inputs = registration_inputs(ctx, method)
    origin = inputs.tgt.mean(axis=0)
    init_world = np.eye(4) if p.initial is None else np.asarray(p.initial, dtype=np.float64)
    init_local = shifted(init_world, -origin)
    t_local, _, rmse, _ = icp_schedule(inputs.src, inputs.tgt, inputs.schedule, p.iterations, method, init_local,
                                       origin)
    return registration_result(ctx, inputs, inputs.src, t_local, origin, rmse, method)


class GicpParams(ScheduleParams):
    """Generalized-ICP, coarse to fine."""


class PointToPlaneParams(ScheduleParams):
    """Point-to-plane ICP, coarse to fine."""


def gicp(ctx: StageContext) -> dict[str, Any]:
    """Generalized-ICP to the twin's geometry."""
    return icp(ctx, "gicp")


def point_to_plane(ctx: StageContext) -> dict[str, Any]:
    """Point-to-plane ICP to the twin's geometry."""
    return icp(ctx, "point_to_plane")


GICP = family_stage("registrar", name="gicp", version="2.0.0", params=GicpParams, run=gicp,
                    description="Generalized-ICP to the twin's geometry, coarse to fine (Open3D).")
POINT_TO_PLANE = family_stage("registrar", name="point_to_plane", version="2.0.0", params=PointToPlaneParams,
                              run=point_to_plane,
                              description="Point-to-plane ICP to the twin's geometry, coarse to fine (Open3D).")
