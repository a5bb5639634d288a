"""``calibrated``: the isotropic σ of a profile written by ``gdt calibrate`` (scans of a known object)."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gdt_pipeline import GaussianUncertainty, StageContext
from gdt_pipeline.sensors import load_profile

from ._select import map_selected


class CalibratedParams(BaseModel):
    """The isotropic σ from a calibrated sensor profile (``gdt calibrate`` writes it)."""

    model_config = ConfigDict(extra="forbid")
    profile: str = Field(description="Profile YAML file (relative to the workflow) written by `gdt calibrate`.")
    datasets: list[str] | None = Field(None, description="Apply only to these recent datasets (default: all).")


def calibrated(ctx: StageContext) -> dict[str, Any]:
    """Every selected recent dataset gets the profile's isotropic σ."""
    profile = load_profile(ctx.params.profile, ctx.epoch.workflow_dir)
    units = ctx.epoch.units
    unc = GaussianUncertainty.isotropic(profile.isotropic_sigma(units))
    ctx.log.info("calibrated sigma %.6g %s from profile %s", float(np.sqrt(unc.cov[0, 0, 0])), units, profile.name)
    return {"recent": map_selected(ctx, lambda d: d.with_uncertainty(unc))}
