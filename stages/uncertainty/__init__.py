"""Uncertainty estimators (paper Sec. 3), each a stage:

- ``constant``: one value for a whole dataset: isotropic or anisotropic Gaussian, or GUM rectangular error limits
  (a uniform tolerance box) for CAD whose manufacturing distribution is unknown;
- ``calibrated``: the isotropic σ of a profile written by ``gdt calibrate`` (scans of a known object);
- ``sensor_model``: per point from the sensor pose: range noise along the beam growing with range and incidence,
  lateral noise across it (a full rotated covariance per point), from a preset or a profile file;
- ``voxel_mle``: sample-based, for dense noisy clouds: maximum-likelihood Gaussians on an overlapping voxel grid,
  which replace the points as the dataset's elements;
- ``registration_propagation``: adds the registrar's transform covariance to every element (as M3C2-EP).

Each stage module declares its own ``StageSpec``; this package collects them.
"""

from __future__ import annotations

from gdt_pipeline import StageSpec, hookimpl

from . import calibrated, constant, registration_propagation, sensor_model, voxel_mle
from .calibrated import CalibratedParams
from .constant import ConstantParams
from .registration_propagation import PropagationParams
from .sensor_model import SensorModelParams
from .voxel_mle import VoxelMleParams

__all__ = ["CalibratedParams", "ConstantParams", "PropagationParams", "SensorModelParams", "VoxelMleParams",
           "gdt_stages"]


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in uncertainty estimators."""
    return [constant.SPEC, calibrated.SPEC, sensor_model.SPEC, voxel_mle.SPEC, registration_propagation.SPEC]
