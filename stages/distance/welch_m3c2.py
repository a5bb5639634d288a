"""``welch_m3c2``: the M3C2-style test on equal means along the local normal, with known variances
(t = nᵀd / √(nᵀΣ₁n + nᵀΣ₂n), two-sided p-value), as a baseline inside the pipeline.

The normal is a mesh's facet normal (the recent facet's, else the reference facet's), or for point clouds on both
sides the recent cloud's PCA normal of its k nearest points, computed about the epoch's origin and declared as a
neighbourhood, so that a tile computes what the whole epoch does (1.2.0: it runs in tiles)."""

from __future__ import annotations

import dataclasses

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveInt
from scipy.special import ndtr

from gdt_pipeline import Dataset, StageContext
from gdt_pipeline.geometry import estimate_normals
from gdt_pipeline.measures import MeasureResult, PairGroup, distance_stage


class WelchParams(BaseModel):
    """The M3C2-style test along the local normal."""

    model_config = ConfigDict(extra="forbid")
    normal_neighbours: PositiveInt = Field(20, description="Neighbours for point-cloud normals when neither side "
                                                           "is a mesh.")


def _cloud_normals(ctx: StageContext, ds: Dataset) -> np.ndarray:
    """PCA normals of a recent point cloud about the epoch's origin (declared as neighbourhoods in a tile)."""
    ctx.k_nearest(ds.points, ctx.params.normal_neighbours)
    return estimate_normals(ds.points, ctx.params.normal_neighbours, ctx.epoch.origin)


def with_normals(ctx: StageContext, groups: list[PairGroup], query: int) -> list[PairGroup]:
    """The pair groups of recent dataset ``query`` with the local normal of each pair."""
    ds = ctx["recent"][query]
    reference = ctx["reference"]
    cloud_normals = None
    out = []
    for g in groups:
        ref = reference.items[int(g.ref_items[0])].dataset
        if ds.faces is not None or ref.faces is not None:
            nrm = (ds.facet_normals(g.elements, unit=True) if ds.faces is not None
                   else ref.facet_normals(g.ref_elements, unit=True))
        else:
            if cloud_normals is None:
                cloud_normals = _cloud_normals(ctx, ds)
            nrm = cloud_normals[g.elements]
        out.append(dataclasses.replace(g, normal=nrm))
    return out


def welch(g: PairGroup, rng: np.random.Generator, params: WelchParams) -> MeasureResult:
    """|t| of each pair along its normal and its two-sided normal p-value."""
    n = len(g.idx)
    along = np.einsum("ij,ij->i", g.normal, g.mu_q - g.mu_r)
    var = np.einsum("ni,nij,nj->n", g.normal, g.u_q.covariance(n) + g.u_r.covariance(n), g.normal)
    t = along / np.sqrt(var)
    return np.abs(t), 2.0 * ndtr(-np.abs(t)), np.zeros(0)


SPEC = distance_stage(name="welch_m3c2", measure=welch, params=WelchParams, version="1.3.0", prepare=with_normals,
                      description="M3C2-style test on equal means along the local normal (known variances).")
