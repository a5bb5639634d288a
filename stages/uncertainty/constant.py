"""``constant``: one value for a whole dataset: isotropic or anisotropic Gaussian, or GUM rectangular error limits
(a uniform tolerance box) for CAD whose manufacturing distribution is unknown."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, model_validator

from gdt_pipeline import BoxUncertainty, GaussianUncertainty, StageContext, family_stage

from ._select import map_selected


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


def constant(ctx: StageContext) -> dict[str, Any]:
    """Every selected recent dataset gets the one uncertainty of the parameters."""
    unc = ctx.params.build()
    return {"recent": map_selected(ctx, lambda d: d.with_uncertainty(unc))}


SPEC = family_stage("uncertainty", name="constant", version="1.0.0", params=ConstantParams, run=constant,
                    tiling="tile",  # each element's model from that element alone
                    description="One Gaussian (isotropic/anisotropic) or tolerance box for a whole dataset.")
