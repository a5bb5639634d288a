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

from gdt_pipeline import StageSpec, hookimpl

from ._icp import ScheduleParams, icp_schedule, source_points, target_points, transform_covariance
from .coarse import CoarseParams, coarse
from .given import GivenParams, given, matrix_problems
from .icp import GicpParams, PointToPlaneParams, gicp, point_to_plane
from .identity import IdentityParams, identity
from .stable_areas import StableAreasParams, stable_areas

__all__ = ["VERSION", "CoarseParams", "GicpParams", "GivenParams", "IdentityParams", "PointToPlaneParams",
           "ScheduleParams", "StableAreasParams", "gdt_stages", "icp_schedule", "source_points", "target_points",
           "transform_covariance"]

VERSION = "1.0.0"


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in registrars."""
    common = {"family": "registrar", "version": VERSION, "requires": ("recent", "reference"),
              "provides": ("recent", "registration")}
    return [
        StageSpec(name="identity", family="registrar", version=VERSION, params=IdentityParams, run=identity,
                  requires=("recent",), provides=("recent", "registration"),
                  description="Keep the recent data where it is (pre-registered input)."),
        StageSpec(name="given", family="registrar", version=VERSION, params=GivenParams, run=given,
                  validate=matrix_problems,
                  requires=("recent",), provides=("recent", "registration"),
                  description="Apply a known 4x4 transform (inline or from a file)."),
        StageSpec(name="gicp", params=GicpParams, run=gicp,
                  description="Generalized-ICP to the twin's geometry, coarse to fine (Open3D).", **common),
        StageSpec(name="point_to_plane", params=PointToPlaneParams, run=point_to_plane,
                  description="Point-to-plane ICP to the twin's geometry, coarse to fine (Open3D).", **common),
        StageSpec(name="coarse", params=CoarseParams, run=coarse,
                  description="FPFH + RANSAC global alignment refined by ICP, for data that starts far off.",
                  **common),
        StageSpec(name="stable_areas", params=StableAreasParams, run=stable_areas,
                  description="ICP on stable areas only (box, and trimming of changed points).", **common),
    ]
