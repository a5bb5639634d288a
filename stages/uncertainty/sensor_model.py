"""``sensor_model``: per point from the sensor pose: range noise along the beam growing with range and incidence,
lateral noise across it (a full rotated covariance per point), from a preset or a profile file; with
``self_calibrate`` the profile's range and lateral terms are first fitted to the epoch's own points on the twin's
meshes (``self_calibration``), once for the whole epoch, tiled or not (the stage's survey)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveInt

from gdt_pipeline import Dataset, GaussianUncertainty, StageContext, family_stage
from gdt_pipeline.geometry import estimate_normals
from gdt_pipeline.sensors import PRESETS, SensorProfile, load_profile, profile_problems

from ._select import map_selected
from .estimators import beam_covariances
from .incidence import TwinFacets, surface_cosines
from .self_calibration import beam_hits, calibrate_profile, fit_data, joined, known_surfaces


class SensorModelParams(BaseModel):
    """Per-point covariance from the sensor pose and a noise profile."""

    model_config = ConfigDict(extra="forbid")
    profile: str = Field(description=f"A preset ({', '.join(PRESETS)}) or a profile YAML file.")
    viewpoint: list[float] | None = Field(None, min_length=3, max_length=3,
                                          description="Sensor position; default: the input's single viewpoint.")
    normal_neighbours: PositiveInt = Field(20, description="Neighbours for point-cloud normals (incidence angle).")
    incidence: bool = Field(True, description="Scale the range noise by 1/cos(incidence).")
    incidence_normals: Literal["auto", "cloud"] = Field(
        "auto", description="auto: a point whose beam crosses a twin facet (CAD or an earlier mesh epoch) within "
                            "its 3 σ takes that facet's incidence, the others the cloud's normals; cloud: always "
                            "the cloud's PCA normals (docs/uncertainty.md).")
    datasets: list[str] | None = Field(None, description="Apply only to these recent datasets (default: all).")
    self_calibrate: bool = Field(False, description="Fit the profile's range and lateral scales to this epoch's "
                                                    "points on the twin's meshes (CAD or earlier mesh epochs) first; "
                                                    "the fit goes into the provenance (docs/uncertainty.md).")
    calibration_points: PositiveInt = Field(200_000, description="Points the self-calibration uses at most (an even "
                                                                 "stride over the selected datasets).")
    calibration_terms: Literal["common", "separate"] = Field(
        "common", description="One scale for the range and lateral terms, or one each (needs grazing views).")
    calibration_min_points: PositiveInt = Field(500, description="Fewer points on known surfaces than this: the "
                                                                 "prior profile is kept, with a warning.")


def station(ds: Dataset, viewpoint: list[float] | None) -> np.ndarray:
    """The one sensor position of a dataset (the stage's ``viewpoint`` first); several or none is an error."""
    if viewpoint is not None:
        return np.asarray(viewpoint, dtype=np.float64)
    if ds.viewpoints is not None and len(ds.viewpoints) == 1:
        return ds.viewpoints[0]
    have = 0 if ds.viewpoints is None else len(ds.viewpoints)
    raise ValueError(f"dataset {ds.name!r}: sensor_model needs one sensor position per dataset (it has {have}):"
                     f" put a pose file beside the scan (<scan>_pose.json with a viewpoint), read a format "
                     f"that carries it (E57), give the input `viewpoints: [[x, y, z]]`, or split a "
                     f"multi-station scan per station (docs/formats.md)")


def sensor_survey(params: SensorModelParams, slots: Mapping[str, Any]) -> dict[str, Any]:
    """With ``self_calibrate``: the profile fitted to the epoch's points on the twin's meshes, and the fit's record
    (whole-epoch figures: every tile uses the same profile)."""
    if not params.self_calibrate:
        return {}
    epoch = slots["epoch"]
    prior = load_profile(params.profile, epoch.workflow_dir)
    surfaces = known_surfaces(slots.get("reference"))
    recent = [ds for ds in slots["recent"] if params.datasets is None or ds.name in params.datasets]
    stride = max(1, math.ceil(sum(ds.n_elements for ds in recent) / params.calibration_points))
    shift = np.zeros(3) if epoch.origin is None else np.asarray(epoch.origin, dtype=np.float64)
    parts = []
    for ds in recent if surfaces else []:
        pos, origin = ds.element_positions()[::stride], station(ds, params.viewpoint)
        hit_range, normals, ref_var = beam_hits(surfaces, origin, pos, shift)
        parts.append(fit_data(pos, origin, hit_range, normals, ref_var, prior, epoch.units))
    found = calibrate_profile(prior, joined(parts), params.calibration_min_points,
                              separate=params.calibration_terms == "separate")
    record = found.record if surfaces else {**found.record, "why": "the twin holds no mesh to calibrate against "
                                                                  "(a CAD model or a mesh epoch): prior kept"}
    return {"profile": found.profile.model_dump(mode="json"), "self_calibration": record}


def sensor_model(ctx: StageContext) -> dict[str, Any]:
    """Per-point covariances of the selected recent datasets from their sensor position and the profile."""
    if "profile" in ctx.survey:
        profile = SensorProfile.model_validate(ctx.survey["profile"])
    else:
        profile = load_profile(ctx.params.profile, ctx.epoch.workflow_dir)
    if "self_calibration" in ctx.survey:
        ctx.report(self_calibration=ctx.survey["self_calibration"])
    units = ctx.epoch.units

    shift = np.zeros(3) if ctx.epoch.origin is None else np.asarray(ctx.epoch.origin, dtype=np.float64)
    facets = TwinFacets.of(ctx.get("reference"), shift) if ctx.params.incidence_normals == "auto" else None
    on_twin: list[float] = []

    def estimate(ds: Dataset) -> Dataset:
        origin = station(ds, ctx.params.viewpoint)
        pos = ds.element_positions()
        beam_range = np.linalg.norm(pos - origin, axis=1)
        cos = incidence_cosines(ctx, ds, origin, profile, facets, on_twin) if ctx.params.incidence else None
        s_range, s_lat = profile.sigmas(beam_range, cos, units)
        return ds.with_uncertainty(GaussianUncertainty(beam_covariances(pos, origin, s_range, s_lat),
                                                         dof=profile.dof))

    recent = map_selected(ctx, estimate)
    if on_twin:
        ctx.report(incidence={"on_twin_surfaces": [round(x, 4) for x in on_twin]})
    return {"recent": recent}


def incidence_cosines(ctx: StageContext, ds: Dataset, origin: np.ndarray, profile: SensorProfile,
                      facets: TwinFacets | None, on_twin: list[float]) -> np.ndarray:
    """Per element cos of the incidence: a mesh's own facets; a point cloud's from the twin's ``facets`` where its
    beam crosses one within 3 σ (the share that did appended to ``on_twin``), elsewhere its PCA normals."""
    pos = ds.element_positions()
    beam = pos - origin
    unit = beam / np.maximum(np.linalg.norm(beam, axis=1, keepdims=True), 1e-300)
    if ds.faces is not None:
        return np.einsum("ij,ij->i", ds.facet_normals(unit=True), unit)
    cos = np.full(len(pos), np.nan)
    if facets is not None:
        cos, reach = surface_cosines(facets, origin, pos, profile, ctx.epoch.units)
        ctx.neighbourhoods(ds.points, reach)
        on_twin.append(float(np.mean(np.isfinite(cos))) if len(cos) else 0.0)
    if np.all(np.isfinite(cos)):
        return cos
    normals = estimate_normals(ds.points, ctx.params.normal_neighbours, ctx.epoch.origin)
    ctx.k_nearest(ds.points, ctx.params.normal_neighbours)  # in a tile, the runner checks each was whole
    return np.where(np.isfinite(cos), cos, np.einsum("ij,ij->i", normals, unit))


def profile_problems_any(params: SensorModelParams, base: Path) -> list[tuple[str, str]]:
    """The profile, checked before a run: a preset or a readable, valid profile file."""
    return [("profile", m) for m in profile_problems(params.profile, base)]


SPEC = family_stage("uncertainty", name="sensor_model", version="1.1.0", params=SensorModelParams, run=sensor_model,
                    validate=profile_problems_any, survey=sensor_survey, optional=("reference",), tiling="tile",
                    description="Per-point covariance from sensor pose, range and incidence (preset or profile), "
                                "optionally self-calibrated against the twin's meshes.")
