"""``voxel_mle``: sample-based, for dense noisy clouds: maximum-likelihood Gaussians on an overlapping voxel grid,
which replace the points as the dataset's elements."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat

from gdt_pipeline import Dataset, GaussianUncertainty, StageContext, family_stage

from . import estimators
from ._select import map_selected


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


def voxel_mle(ctx: StageContext) -> dict[str, Any]:
    """The selected point clouds replaced by maximum-likelihood Gaussians on an overlapping voxel grid."""
    p = ctx.params
    steps = max(1, round(1.0 / (1.0 - p.overlap)))
    floor = p.min_sigma if p.min_sigma is not None else p.voxel / 100.0

    def estimate(ds: Dataset) -> Dataset:
        if ds.faces is not None:
            raise ValueError(f"dataset {ds.name!r} is a mesh; voxel_mle estimates Gaussians from point samples")
        mean, cov, counts = estimators.voxel_mle(ds.points, p.voxel, steps, p.min_points, floor)
        if len(mean) == 0:
            raise ValueError(f"dataset {ds.name!r}: no voxel of edge {p.voxel} holds {p.min_points} points")
        ctx.log.info("%s: %d points -> %d voxel Gaussians (overlap %.3g, median %d points each)", ds.name,
                     len(ds.points), len(mean), 1 - 1 / steps, int(np.median(counts)))
        return dataclasses.replace(ds, points=mean, uncertainty=GaussianUncertainty(cov))

    return {"recent": map_selected(ctx, estimate)}


SPEC = family_stage("uncertainty", name="voxel_mle", version="1.0.0", params=VoxelMleParams, run=voxel_mle,
                    description="Maximum-likelihood Gaussians on an overlapping voxel grid (dense noisy clouds).")
