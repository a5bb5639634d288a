"""``registration_propagation``: adds the registrar's transform covariance to every element (as M3C2-EP does)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from gdt_pipeline import Dataset, GaussianUncertainty, StageContext, family_stage

from ._select import map_selected, selected
from .estimators import propagate_registration


class PropagationParams(BaseModel):
    """Add the registration's uncertainty to every element's covariance."""

    model_config = ConfigDict(extra="forbid")
    non_gaussian: Literal["error", "moment_match"] = Field(
        "error", description="A box or mixture plus a Gaussian is no longer a box: stop, or continue with the "
                             "Gaussian of the summed covariance.")
    datasets: list[str] | None = Field(None, description="Apply only to these recent datasets (default: all).")


def registration_propagation(ctx: StageContext) -> dict[str, Any]:
    """The registration's covariance added to every element of the selected recent datasets."""
    reg = ctx["registration"]
    recent, _ = selected(ctx)
    if reg.covariance is None:
        ctx.log.warning("registration %r has no covariance: nothing to propagate", reg.method)
        return {"recent": recent}

    def add_registration(ds: Dataset) -> Dataset:
        unc = ds.uncertainty
        if unc is None:
            raise ValueError(f"dataset {ds.name!r} has no uncertainty to add the registration's to")
        if not isinstance(unc, GaussianUncertainty) and ctx.params.non_gaussian == "error":
            raise ValueError(f"dataset {ds.name!r} has a {unc.model!r} uncertainty; adding a Gaussian registration "
                             f"error to it is not a {unc.model} (set `non_gaussian: moment_match`)")
        extra = propagate_registration(ds.element_positions() - reg.center, reg.covariance)
        return ds.with_uncertainty(GaussianUncertainty(ds.element_covariance() + extra))

    return {"recent": map_selected(ctx, add_registration)}


SPEC = family_stage("uncertainty", name="registration_propagation", version="1.0.0", params=PropagationParams,
                    run=registration_propagation, requires=("recent", "registration"), tiling="tile",
                    description="Add the registration's transform covariance to every element (as M3C2-EP).")
