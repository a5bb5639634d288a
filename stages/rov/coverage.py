"""``coverage``: a region of view for data without stations (airborne LiDAR, voxelised or merged clouds), judged per
known element from the recent data alone.

- **Matched** (present): a recent point lies within the 99 % region of the pair (Mahalanobis distance under the sum
  of both covariances, χ²₃ at 0.99); with a ``sight``, also one of the 8 recent points nearest across the sight
  within one recent spacing, at the element's depth along it (χ²₁ at 0.99), since sparse airborne data samples
  the same surface a spacing apart.
- **Removed** needs evidence that the place is empty now:
  - with a stated ``sight`` (the direction the beams travel, e.g. ``[0, 0, -1]`` for nadir airborne data): every
    recent return in the element's column (the cells of ``spacings`` recent spacings across around it, across the
    sight) lies beyond it along the sight, so every beam there passed its place;
  - without one: the recent cloud samples the element's surroundings (a recent point within its 99 % radius plus
    ``spacings`` recent spacings: the ``gdt_pipeline.coverage`` test) but has nothing at the element itself.
    This trusts that a sensor that saw the surroundings would have seen the element: state a ``sight`` where
    occlusion matters.
- **Not seen** (outside the region of view) otherwise: no recent data there, or something in front of the element
  along the sight.

The volume is the recent data's bounding box, grown by the same neighbourhood.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, field_validator
from scipy.spatial import cKDTree

from gdt_pipeline import CompositeItem, Dataset, ItemView, RegionOfView, StageContext, family_stage
from gdt_pipeline.coverage import sampled, within_pair_region
from gdt_pipeline.region_of_view import point_spacing, view_frame
from gdt_pipeline.types.region99 import CHI2_3_99

CHI2_1_99 = 6.634896601021214  # chi-square quantile, 1 degree of freedom, p = 0.99 (scipy.stats.chi2.ppf)
NEIGHBOURS = 8


class CoverageParams(BaseModel):
    """A region of view from the recent data's own coverage, optionally along a stated sight direction."""

    model_config = ConfigDict(extra="forbid")
    sight: list[float] | None = Field(
        None, min_length=3, max_length=3,
        description="Direction the recent sensor's beams travel, e.g. [0, 0, -1] for nadir airborne LiDAR. Then a "
                    "known element is removed only where every recent return around it lies beyond it along this "
                    "direction. Default: none (removed where the recent cloud samples the surroundings but has "
                    "nothing at the element).")
    spacings: PositiveFloat = Field(3.0, description="Neighbourhood, in recent point spacings, that must hold "
                                                     "recent data for an element to count as seen.")

    @field_validator("sight")
    @classmethod
    def _unit(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and not np.linalg.norm(v) > 0:
            raise ValueError("sight must be a non-zero direction")
        return v


class Judged(NamedTuple):
    """Per known element: matched (present), and seen (matched, or evidence that its place is empty)."""

    matched: np.ndarray
    seen: np.ndarray


def _cloud(recent: list[Dataset]) -> tuple[np.ndarray, np.ndarray]:
    """The recent elements' positions and covariances, every dataset together."""
    pos = [ds.element_positions() for ds in recent]
    cov = [ds.element_covariance() if ds.uncertainty is not None else np.zeros((ds.n_elements, 3, 3))
           for ds in recent]
    return np.concatenate(pos), np.concatenate(cov)


def _matched_along(points: np.ndarray, cov: np.ndarray, cloud: np.ndarray, cloud_cov: np.ndarray, sight: np.ndarray,
                   radius: float) -> np.ndarray:
    """Whether one of the ``NEIGHBOURS`` recent points nearest across ``sight`` (within ``radius``) lies at the
    element's depth along it, within the pair's 99 % interval: sparse data (airborne, metres apart) samples the
    same surface at other places, so the nearest point in 3-D is rarely within the noise of the element."""
    fwd, right, up = view_frame(sight)
    tree = cKDTree(np.stack([cloud @ right, cloud @ up], axis=1))
    dist, idx = tree.query(np.stack([points @ right, points @ up], axis=1), k=NEIGHBOURS, distance_upper_bound=radius,
                           workers=-1)
    found = np.isfinite(dist)
    idx = np.where(found, idx, 0)
    depth = np.abs(cloud[idx] @ fwd - (points @ fwd)[:, None])
    var = np.einsum("i,nij,j->n", fwd, cov, fwd)[:, None] + np.einsum("i,nkij,j->nk", fwd, cloud_cov[idx], fwd)
    return np.asarray((found & (depth**2 <= CHI2_1_99 * var)).any(axis=1))


def _seen_through(points: np.ndarray, reach: np.ndarray, cloud: np.ndarray, sight: np.ndarray, cell: float
                  ) -> np.ndarray:
    """Whether every recent return in each point's column (3 × 3 cells of ``cell`` across ``sight``) lies beyond
    the point along ``sight`` (and the column holds returns)."""
    fwd, right, up = view_frame(sight)
    def cells(p: np.ndarray) -> np.ndarray:
        return np.floor(np.stack([p @ right, p @ up], axis=1) / cell).astype(np.int64)

    ij = cells(cloud)
    lo = ij.min(axis=0) - 1
    ij -= lo
    width = int(ij[:, 1].max()) + 3
    key = ij[:, 0] * width + ij[:, 1]
    uniq, inverse = np.unique(key, return_inverse=True)
    first = np.full(len(uniq), np.inf)
    np.minimum.at(first, inverse, cloud @ fwd)  # the first return along the sight in each cell
    q = cells(points) - lo
    shallowest = np.full(len(points), np.inf)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            k = (q[:, 0] + di) * width + q[:, 1] + dj
            at = np.clip(np.searchsorted(uniq, k), 0, len(uniq) - 1)
            shallowest = np.minimum(shallowest, np.where(uniq[at] == k, first[at], np.inf))
    return np.isfinite(shallowest) & (shallowest > points @ fwd + reach)


def judge(item: CompositeItem, cloud: np.ndarray, cloud_cov: np.ndarray, params: CoverageParams, spacing: float
          ) -> Judged:
    """Matched and seen per element of one known item."""
    ds = item.dataset
    points = ds.element_positions()
    cov = ds.element_covariance() if ds.uncertainty is not None else np.zeros((ds.n_elements, 3, 3))
    matched = within_pair_region(points, cov, cloud, cloud_cov)
    reach = np.sqrt(CHI2_3_99 * np.linalg.eigvalsh(cov)[:, -1].clip(0.0))
    if params.sight is not None:
        sight = np.asarray(params.sight, dtype=np.float64) / np.linalg.norm(params.sight)
        matched |= _matched_along(points, cov, cloud, cloud_cov, sight, spacing)
        empty = _seen_through(points, reach, cloud, sight, params.spacings * spacing)
    else:
        empty = sampled(cloud, points, reach, params.spacings).covered
    return Judged(matched, matched | empty)


def coverage(ctx: StageContext) -> dict[str, Any]:
    """Judge every known element from the recent data's own coverage (see the module's docstring)."""
    p = ctx.params
    cloud, cloud_cov = _cloud(list(ctx["recent"]))
    if not len(cloud):
        raise ValueError("coverage: the recent datasets hold no elements")
    spacing = point_spacing(cloud)
    margin = p.spacings * spacing
    region = RegionOfView.box(cloud.min(axis=0) - margin, cloud.max(axis=0) + margin)
    views, counts = {}, {"matched": 0, "removed": 0, "not_seen": 0}
    reference = ctx.get("reference")
    for it in [] if reference is None else reference.items:
        found = judge(it, cloud, cloud_cov, p, spacing)
        views[it.key] = ItemView(in_view=found.seen, matched=found.matched)
        vis = it.visible
        counts["matched"] += int((found.matched & vis).sum())
        counts["removed"] += int((found.seen & ~found.matched & vis).sum())
        counts["not_seen"] += int((~found.seen & vis).sum())
    evidence = "sight " + str(p.sight) if p.sight is not None else "the recent cloud's own coverage"
    ctx.log.info("coverage (%s, spacing %.4g): %s", evidence, spacing, counts)
    ctx.report(evidence=evidence, spacing=spacing, **counts)
    method = f"coverage: recent bounding box; removal from {evidence}"
    return {"rov": RegionOfView(region.vertices, region.faces, views=views, method=method)}


SPEC = family_stage("rov", name="coverage", version="1.0.0", params=CoverageParams, run=coverage,
                    optional=("reference",),
                    description="Region of view without stations: from the recent data's own coverage, or along a "
                                "stated sight direction (nadir airborne data).")
