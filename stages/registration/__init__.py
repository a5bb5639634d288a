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
covariances and box axes rotated with them). Each stage module declares its own ``StageSpec``; this package
collects them.
"""

from __future__ import annotations

from gdt_pipeline import StageSpec, hookimpl

from . import coarse, given, icp, identity, stable_areas
from ._icp import ScheduleParams, icp_schedule, source_points, target_points
from .coarse import CoarseParams
from .given import GivenParams
from .icp import GicpParams, PointToPlaneParams
from .identity import IdentityParams
from .stable_areas import StableAreasParams

__all__ = ["CoarseParams", "GicpParams", "GivenParams", "IdentityParams", "PointToPlaneParams", "ScheduleParams",
           "StableAreasParams", "gdt_stages", "icp_schedule", "source_points", "target_points"]


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in registrars."""
    return [identity.SPEC, given.SPEC, icp.GICP, icp.POINT_TO_PLANE, coarse.SPEC, stable_areas.SPEC]
