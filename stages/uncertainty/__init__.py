"""Uncertainty estimators (paper Sec. 3), each a stage:

- ``constant``: one value for a whole dataset: isotropic or anisotropic Gaussian, or GUM rectangular error limits
  (a uniform tolerance box) for CAD whose manufacturing distribution is unknown;
- ``calibrated``: the isotropic σ of a profile written by ``gdt calibrate`` (scans of a known object);
- ``sensor_model``: per point from the sensor pose: range noise along the beam growing with range and incidence,
  lateral noise across it (a full rotated covariance per point), from a preset or a profile file;
- ``voxel_mle``: sample-based, for dense noisy clouds: maximum-likelihood Gaussians on an overlapping voxel grid,
  which replace the points as the dataset's elements;
- ``registration_propagation``: adds the registrar's transform covariance to every element (as M3C2-EP does).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gdt_pipeline import StageSpec, hookimpl
from gdt_pipeline.sensors import profile_problems

from .calibrated import CalibratedParams, calibrated
from .constant import ConstantParams, constant
from .registration_propagation import PropagationParams, registration_propagation
from .sensor_model import SensorModelParams, sensor_model, sensor_survey
from .voxel_mle import VoxelMleParams, voxel_mle

__all__ = ["CalibratedParams", "ConstantParams", "PropagationParams", "SensorModelParams", "VoxelMleParams",
           "gdt_stages"]


def _profile_isotropic(params: Any, base: Path) -> list[tuple[str, str]]:
    """`calibrated`'s profile, checked before a run: a readable, valid, isotropic profile."""
    return [("profile", m) for m in profile_problems(params.profile, base, isotropic=True)]


def _profile(params: Any, base: Path) -> list[tuple[str, str]]:
    """`sensor_model`'s profile, checked before a run: a preset or a readable, valid profile file."""
    return [("profile", m) for m in profile_problems(params.profile, base)]


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in uncertainty estimators."""
    common = {"family": "uncertainty", "version": "1.0.0", "requires": ("recent",), "provides": ("recent",)}
    tiled = {**common, "tiling": "tile"}  # each element's model from that element alone
    return [
        StageSpec(name="constant", params=ConstantParams, run=constant,
                  description="One Gaussian (isotropic/anisotropic) or tolerance box for a whole dataset.", **tiled),
        StageSpec(name="calibrated", params=CalibratedParams, run=calibrated, validate=_profile_isotropic,
                  description="Isotropic σ of a profile from `gdt calibrate` (scans of a known object).", **tiled),
        StageSpec(name="sensor_model", params=SensorModelParams, run=sensor_model, validate=_profile,
                  survey=sensor_survey, optional=("reference",),
                  description="Per-point covariance from sensor pose, range and incidence (preset or profile), "
                              "optionally self-calibrated against the twin's meshes.", **tiled),
        StageSpec(name="voxel_mle", params=VoxelMleParams, run=voxel_mle,
                  description="Maximum-likelihood Gaussians on an overlapping voxel grid (dense noisy clouds).",
                  **common),
        StageSpec(name="registration_propagation", family="uncertainty", version="1.0.0", params=PropagationParams,
                  run=registration_propagation, requires=("recent", "registration"), provides=("recent",),
                  tiling="tile",
                  description="Add the registration's transform covariance to every element (as M3C2-EP)."),
    ]
