"""``sensor_model``: per point from the sensor pose: range noise along the beam growing with range and incidence,
lateral noise across it (a full rotated covariance per point), from a preset or a profile file."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveInt

from gdt_pipeline import Dataset, GaussianUncertainty, StageContext
from gdt_pipeline.geometry import estimate_normals, knn_reach
from gdt_pipeline.sensors import PRESETS, load_profile

from ._select import map_selected
from .estimators import beam_covariances


class SensorModelParams(BaseModel):
    """Per-point covariance from the sensor pose and a noise profile."""

    model_config = ConfigDict(extra="forbid")
    profile: str = Field(description=f"A preset ({', '.join(PRESETS)}) or a profile YAML file.")
    viewpoint: list[float] | None = Field(None, min_length=3, max_length=3,
                                          description="Sensor position; default: the input's single viewpoint.")
    normal_neighbours: PositiveInt = Field(20, description="Neighbours for point-cloud normals (incidence angle).")
    incidence: bool = Field(True, description="Scale the range noise by 1/cos(incidence).")
    datasets: list[str] | None = Field(None, description="Apply only to these recent datasets (default: all).")


def sensor_model(ctx: StageContext) -> dict[str, Any]:
    """Per-point covariances of the selected recent datasets from their sensor position and the profile."""
    profile = load_profile(ctx.params.profile, ctx.epoch.workflow_dir)
    units = ctx.epoch.units

    def estimate(ds: Dataset) -> Dataset:
        if ctx.params.viewpoint is not None:
            origin = np.asarray(ctx.params.viewpoint, dtype=np.float64)
        elif ds.viewpoints is not None and len(ds.viewpoints) == 1:
            origin = ds.viewpoints[0]
        else:
            have = 0 if ds.viewpoints is None else len(ds.viewpoints)
            raise ValueError(f"dataset {ds.name!r}: sensor_model needs one sensor position per dataset (it has {have}):"
                             f" put a pose file beside the scan (<scan>_pose.json with a viewpoint), read a format "
                             f"that carries it (E57), give the input `viewpoints: [[x, y, z]]`, or split a "
                             f"multi-station scan per station (docs/formats.md)")
        pos = ds.element_positions()
        beam = pos - origin
        beam_range = np.linalg.norm(beam, axis=1)
        cos = None
        if ctx.params.incidence:
            if ds.faces is not None:
                normals = ds.facet_normals(unit=True)
            else:
                normals = estimate_normals(ds.points, ctx.params.normal_neighbours, ctx.epoch.origin)
                if ctx.tile is not None:  # in a tile: the runner checks that every neighbourhood was whole
                    ctx.neighbourhoods(ds.points, knn_reach(ds.points, ctx.params.normal_neighbours))
            cos = np.einsum("ij,ij->i", normals, beam / np.maximum(beam_range[:, None], 1e-300))
        s_range, s_lat = profile.sigmas(beam_range, cos, units)
        return ds.with_uncertainty(GaussianUncertainty(beam_covariances(pos, origin, s_range, s_lat)))

    return {"recent": map_selected(ctx, estimate)}
