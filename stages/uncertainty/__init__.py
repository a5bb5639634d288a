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

import dataclasses
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt, model_validator

from gdt_pipeline import (
    BoxUncertainty,
    Dataset,
    GaussianUncertainty,
    StageContext,
    StageSpec,
    hookimpl,
)
from gdt_pipeline.geometry import estimate_normals
from gdt_pipeline.sensors import PRESETS, load_profile

from .estimators import beam_covariances, propagate_registration, voxel_mle

Vec3 = list[float]
Mat3 = list[list[float]]


class ConstantParams(BaseModel):
    """One uncertainty for every element of the recent datasets (or of the datasets named)."""

    model_config = ConfigDict(extra="forbid")
    model: Literal["isotropic", "anisotropic", "box"] = Field(
        "isotropic", description="isotropic: sigma; anisotropic: covariance, or sigmas (+ rotation); "
                                 "box: half_widths (+ rotation), GUM error limits")
    sigma: PositiveFloat | None = Field(None, description="Standard deviation in twin units (isotropic).")
    sigmas: list[PositiveFloat] | None = Field(None, min_length=3, max_length=3,
                                               description="Standard deviations along the axes (anisotropic).")
    covariance: list[list[float]] | None = Field(None, description="Full 3x3 covariance (anisotropic).")
    half_widths: list[PositiveFloat] | None = Field(None, min_length=3, max_length=3,
                                                    description="Tolerance half-widths in twin units (box).")
    rotation: list[list[float]] | None = Field(None, description="3x3 rotation whose columns are the axes of "
                                                                 "sigmas or of the box (default: world axes).")
    datasets: list[str] | None = Field(None, description="Apply only to these recent datasets (default: all).")

    @model_validator(mode="after")
    def _complete(self) -> ConstantParams:
        need = {"isotropic": ["sigma"], "box": ["half_widths"]}.get(self.model, [])
        for name in need:
            if getattr(self, name) is None:
                raise ValueError(f"model {self.model!r} needs {name!r}")
        if self.model == "anisotropic" and (self.covariance is None) == (self.sigmas is None):
            raise ValueError("model 'anisotropic' needs exactly one of 'covariance' or 'sigmas'")
        if self.covariance is not None:
            cov = np.asarray(self.covariance, dtype=float)
            if cov.shape != (3, 3) or not np.allclose(cov, cov.T):
                raise ValueError("covariance must be a symmetric 3x3 matrix")
            if np.linalg.eigvalsh(cov).min() <= 0:
                raise ValueError("covariance must be positive definite")
        if self.rotation is not None:
            rot = np.asarray(self.rotation, dtype=float)
            if rot.shape != (3, 3) or not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6):
                raise ValueError("rotation must be an orthonormal 3x3 matrix")
        return self

    def build(self) -> GaussianUncertainty | BoxUncertainty:
        """The uncertainty these parameters describe (one shared value)."""
        rot = None if self.rotation is None else np.asarray(self.rotation, dtype=float)
        if self.model == "isotropic":
            return GaussianUncertainty.isotropic(float(self.sigma))
        if self.model == "box":
            return BoxUncertainty(np.asarray([self.half_widths]), None if rot is None else rot[None])
        if self.covariance is not None:
            return GaussianUncertainty(np.asarray(self.covariance, dtype=float)[None])
        cov = np.diag(np.square(self.sigmas))
        if rot is not None:
            cov = rot @ cov @ rot.T
        return GaussianUncertainty(((cov + cov.T) / 2)[None])


def _selected(ctx: StageContext) -> tuple[list[Dataset], set[str]]:
    """The recent datasets, and the names this stage applies to (its ``datasets`` param, default all)."""
    recent = list(ctx["recent"])
    names = ctx.params.datasets
    if names is None:
        return recent, {d.name for d in recent}
    unknown = sorted(set(names) - {d.name for d in recent})
    if unknown:
        raise ValueError(f"datasets {unknown} are not in this epoch (have: {[d.name for d in recent]})")
    return recent, set(names)


def _constant(ctx: StageContext) -> dict[str, Any]:
    unc = ctx.params.build()
    recent, names = _selected(ctx)
    return {"recent": [d.with_uncertainty(unc) if d.name in names else d for d in recent]}


class CalibratedParams(BaseModel):
    """The isotropic σ from a calibrated sensor profile (``gdt calibrate`` writes it)."""

    model_config = ConfigDict(extra="forbid")
    profile: str = Field(description="Profile YAML file (relative to the workflow) written by `gdt calibrate`.")
    datasets: list[str] | None = Field(None, description="Apply only to these recent datasets (default: all).")


def _calibrated(ctx: StageContext) -> dict[str, Any]:
    profile = load_profile(ctx.params.profile, ctx.epoch.workflow_dir)
    units = ctx.epoch.units
    unc = GaussianUncertainty.isotropic(profile.isotropic_sigma(units))
    recent, names = _selected(ctx)
    ctx.log.info("calibrated sigma %.6g %s from profile %s", float(np.sqrt(unc.cov[0, 0, 0])), units, profile.name)
    return {"recent": [d.with_uncertainty(unc) if d.name in names else d for d in recent]}


class SensorModelParams(BaseModel):
    """Per-point covariance from the sensor pose and a noise profile."""

    model_config = ConfigDict(extra="forbid")
    profile: str = Field(description=f"A preset ({', '.join(PRESETS)}) or a profile YAML file.")
    viewpoint: list[float] | None = Field(None, min_length=3, max_length=3,
                                          description="Sensor position; default: the input's single viewpoint.")
    normal_neighbours: PositiveInt = Field(20, description="Neighbours for point-cloud normals (incidence angle).")
    incidence: bool = Field(True, description="Scale the range noise by 1/cos(incidence).")
    datasets: list[str] | None = Field(None, description="Apply only to these recent datasets (default: all).")


def _sensor_model(ctx: StageContext) -> dict[str, Any]:
    profile = load_profile(ctx.params.profile, ctx.epoch.workflow_dir)
    units = ctx.epoch.units
    recent, names = _selected(ctx)
    out = []
    for ds in recent:
        if ds.name not in names:
            out.append(ds)
            continue
        if ctx.params.viewpoint is not None:
            origin = np.asarray(ctx.params.viewpoint, dtype=np.float64)
        elif ds.viewpoints is not None and len(ds.viewpoints) == 1:
            origin = ds.viewpoints[0]
        else:
            have = 0 if ds.viewpoints is None else len(ds.viewpoints)
            raise ValueError(f"dataset {ds.name!r}: sensor_model needs one sensor position per dataset (it has {have}):"
                             f" give the input `viewpoints: [[x, y, z]]`, or split a multi-station scan per station")
        pos = ds.element_positions()
        beam = pos - origin
        rng_ = np.linalg.norm(beam, axis=1)
        cos = None
        if ctx.params.incidence:
            if ds.faces is not None:
                normals = ds.facet_normals(unit=True)
            else:
                normals = estimate_normals(ds.points, ctx.params.normal_neighbours)
            cos = np.einsum("ij,ij->i", normals, beam / np.maximum(rng_[:, None], 1e-300))
        s_range, s_lat = profile.sigmas(rng_, cos, units)
        out.append(ds.with_uncertainty(GaussianUncertainty(beam_covariances(pos, origin, s_range, s_lat))))
    return {"recent": out}


class VoxelMleParams(BaseModel):
    """Maximum-likelihood Gaussians on an overlapping voxel grid (for dense, noisy point clouds)."""

    model_config = ConfigDict(extra="forbid")
    voxel: PositiveFloat = Field(description="Voxel edge length, twin units.")
    overlap: float = Field(0.5, ge=0.0, le=0.9, description="Overlap of neighbouring voxels: the grid is laid "
                                                            "round(1/(1-overlap)) times per axis (0.5 -> 2, 8 voxels "
                                                            "per point).")
    min_points: int = Field(10, ge=4, description="Voxels with fewer points are dropped.")
    min_sigma: PositiveFloat | None = Field(None, description="Floor of the Gaussians' standard deviations (planar "
                                                              "patches); default voxel/100.")
    datasets: list[str] | None = Field(None, description="Apply only to these recent datasets (default: all).")


def _voxel_mle(ctx: StageContext) -> dict[str, Any]:
    p = ctx.params
    steps = max(1, round(1.0 / (1.0 - p.overlap)))
    floor = p.min_sigma if p.min_sigma is not None else p.voxel / 100.0
    recent, names = _selected(ctx)
    out = []
    for ds in recent:
        if ds.name not in names:
            out.append(ds)
            continue
        if ds.faces is not None:
            raise ValueError(f"dataset {ds.name!r} is a mesh; voxel_mle estimates Gaussians from point samples")
        mean, cov, counts = voxel_mle(ds.points, p.voxel, steps, p.min_points, floor)
        if len(mean) == 0:
            raise ValueError(f"dataset {ds.name!r}: no voxel of edge {p.voxel} holds {p.min_points} points")
        ctx.log.info("%s: %d points -> %d voxel Gaussians (overlap %.3g, median %d points each)", ds.name,
                     len(ds.points), len(mean), 1 - 1 / steps, int(np.median(counts)))
        out.append(dataclasses.replace(ds, points=mean, uncertainty=GaussianUncertainty(cov)))
    return {"recent": out}


class PropagationParams(BaseModel):
    """Add the registration's uncertainty to every element's covariance."""

    model_config = ConfigDict(extra="forbid")
    non_gaussian: Literal["error", "moment_match"] = Field(
        "error", description="A box or mixture plus a Gaussian is no longer a box: stop, or continue with the "
                             "Gaussian of the summed covariance.")
    datasets: list[str] | None = Field(None, description="Apply only to these recent datasets (default: all).")


def _registration_propagation(ctx: StageContext) -> dict[str, Any]:
    reg = ctx["registration"]
    recent, names = _selected(ctx)
    if reg.covariance is None:
        ctx.log.warning("registration %r has no covariance: nothing to propagate", reg.method)
        return {"recent": recent}
    out = []
    for ds in recent:
        if ds.name not in names:
            out.append(ds)
            continue
        unc = ds.uncertainty
        if unc is None:
            raise ValueError(f"dataset {ds.name!r} has no uncertainty to add the registration's to")
        if not isinstance(unc, GaussianUncertainty) and ctx.params.non_gaussian == "error":
            raise ValueError(f"dataset {ds.name!r} has a {unc.family!r} uncertainty; adding a Gaussian registration "
                             f"error to it is not a {unc.family} (set `non_gaussian: moment_match`)")
        extra = propagate_registration(ds.element_positions() - reg.center, reg.covariance)
        out.append(ds.with_uncertainty(GaussianUncertainty(ds.element_covariance() + extra)))
    return {"recent": out}


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in uncertainty estimators."""
    common = {"family": "uncertainty", "version": "1.0.0", "requires": ("recent",), "provides": ("recent",)}
    return [
        StageSpec(name="constant", params=ConstantParams, run=_constant,
                  description="One Gaussian (isotropic/anisotropic) or tolerance box for a whole dataset.", **common),
        StageSpec(name="calibrated", params=CalibratedParams, run=_calibrated,
                  description="Isotropic σ of a profile from `gdt calibrate` (scans of a known object).", **common),
        StageSpec(name="sensor_model", params=SensorModelParams, run=_sensor_model,
                  description="Per-point covariance from sensor pose, range and incidence (preset or profile).",
                  **common),
        StageSpec(name="voxel_mle", params=VoxelMleParams, run=_voxel_mle,
                  description="Maximum-likelihood Gaussians on an overlapping voxel grid (dense noisy clouds).",
                  **common),
        StageSpec(name="registration_propagation", family="uncertainty", version="1.0.0", params=PropagationParams,
                  run=_registration_propagation, requires=("recent", "registration"), provides=("recent",),
                  description="Add the registration's transform covariance to every element (as M3C2-EP)."),
    ]
