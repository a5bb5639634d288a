"""``calibrated``: the isotropic σ of a profile written by ``gdt calibrate`` (scans of a known object); a profile with
``dof`` gives a Student t of that scale (heavy tails), one without it a Gaussian."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gdt_pipeline import GaussianUncertainty, StageContext, family_stage
from gdt_pipeline.sensors import load_profile, profile_problems

from ._select import map_selected


class CalibratedParams(BaseModel):
    """The isotropic σ from a calibrated sensor profile (``gdt calibrate`` writes it)."""

    model_config = ConfigDict(extra="forbid")
    profile: str = Field(description="Profile YAML file (relative to the workflow) written by `gdt calibrate`.")
    datasets: list[str] | None = Field(None, description="Apply only to these recent datasets (default: all).")


def calibrated(ctx: StageContext) -> dict[str, Any]:
    """Every selected recent dataset gets the profile's isotropic σ (a Student t's scale when it has ``dof``)."""
    profile = load_profile(ctx.params.profile, ctx.epoch.workflow_dir)
    units = ctx.epoch.units
    unc = GaussianUncertainty.isotropic(profile.isotropic_sigma(units), dof=profile.dof)
    noise = "gaussian" if profile.dof is None else f"student t, nu {profile.dof:.4g}, scale"
    ctx.log.info("calibrated %s sigma %.6g %s from profile %s", noise, float(np.sqrt(unc.cov[0, 0, 0])), units,
                 profile.name)
    ctx.report(model="gaussian" if profile.dof is None else "student_t", dof=profile.dof,
               sigma=float(np.sqrt(unc.cov[0, 0, 0])))
    return {"recent": map_selected(ctx, lambda d: d.with_uncertainty(unc))}


def profile_problems_isotropic(params: CalibratedParams, base: Path) -> list[tuple[str, str]]:
    """The profile, checked before a run: a readable, valid, isotropic profile."""
    return [("profile", m) for m in profile_problems(params.profile, base, isotropic=True)]


SPEC = family_stage("uncertainty", name="calibrated", version="1.1.0", params=CalibratedParams, run=calibrated,
                    validate=profile_problems_isotropic, tiling="tile",
                    description="Isotropic σ of a profile from `gdt calibrate` (scans of a known object); a "
                                "Student t where the profile has heavy tails (dof).")
