"""What every fusion shares about objects: the segmentation parameters, the spread of elements' uncertainty, and the
connected groups (segments) of changed elements."""

from __future__ import annotations

import dataclasses

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from gdt_pipeline import CompositeItem, Dataset, Segment
from gdt_pipeline.geometry.components import radius_components
from gdt_pipeline.geometry.extent import check_radius, radius_within_pairs


class PartParams(BaseModel):
    """A catalogue part to recognise among the new segments."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    name: str = Field(description="The part's name (a part number), recorded on the segments it fits.")
    path: str = Field(description="Its CAD model (any mesh format trimesh reads; relative to the workflow file), "
                                  "in the part's own frame and the workflow's units.")
    max_rms: float | None = Field(None, gt=0, description="Largest RMS point-to-surface distance of a fit it "
                                                          "accepts (default: 2 % of the part's diagonal).")


class SegmentParams(BaseModel):
    """How changed elements are grouped into objects (every fusion)."""

    model_config = ConfigDict(extra="forbid")
    parts: list[PartParams] = Field(default_factory=list, description="Catalogue parts fitted to every new segment "
                                                                      "(multi-start ICP): the segment records the "
                                                                      "part whose model fits, its pose and centre.")
    segment_radius: float | None = Field(None, gt=0, description="Elements closer than this are one object "
                                                                 "(default: 3 × their typical spacing, at least "
                                                                 "1.5σ of their largest axis up to 5 % of their "
                                                                 "extent).")
    min_segment_size: int = Field(10, ge=1, description="Segments with fewer elements are reported as artefacts.")
    whole_parts: bool = Field(True, description="A part of the twin (one mesh item, e.g. one CAD solid) of which a "
                                                "station saw at least a tenth of the area and all of that through "
                                                "(none of it present) is removed whole: its unseen faces too.")
    moved: bool = Field(True, description="Where a removed segment is one part of the twin and that part's own model "
                                          "fits a new segment (multi-start ICP), record the new segment as the part "
                                          "moved, with its displacement.")


# elements whose covariances ``spread`` evaluates at a time
SPREAD_PIECE = 262_144


def spread(ds: Dataset, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """√det Σ (the volume of the error ellipsoid) and the largest-axis σ of the given elements, from one covariance
    evaluation; inf and 0 where the dataset carries no uncertainty (it can never be the more precise)."""
    if ds.uncertainty is None:
        return np.full(len(idx), np.inf), np.zeros(len(idx))
    covariance = ds.element_covariance()
    volume, sigma = np.empty(len(idx)), np.empty(len(idx))
    # in pieces: a copy of every unchanged point's covariance and LAPACK's working copies were 0.6 GB at 10 M points
    for start in range(0, len(idx), SPREAD_PIECE):
        piece = slice(start, start + SPREAD_PIECE)
        cov = covariance[idx[piece]]
        volume[piece] = np.sqrt(np.maximum(np.linalg.det(cov), 0.0))
        sigma[piece] = np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, -1], 0.0))
    return volume, sigma


def _masked_elements(items: list[CompositeItem], masks: dict[int, np.ndarray]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Positions, owning item, element index, score and largest-axis σ of the masked elements of all items, stacked
    (None when no element is masked)."""
    pos, owner, elem, score, sig = [], [], [], [], []
    for i, mask in masks.items():
        idx = np.flatnonzero(mask)
        if not idx.size:
            continue
        ds = items[i].dataset
        pos.append(ds.element_positions()[idx])
        owner.append(np.full(idx.size, i))
        elem.append(idx)
        score.append(items[i].score[idx])
        sig.append(spread(ds, idx)[1])
    if not pos:
        return None
    return np.vstack(pos), np.concatenate(owner), np.concatenate(elem), np.concatenate(score), np.concatenate(sig)


def segment_labels(pos_a: np.ndarray, sig_a: np.ndarray, params: SegmentParams) -> np.ndarray:
    """Connected-component label of each element in the graph of elements closer than the segment radius."""
    tree = cKDTree(pos_a)
    radius = params.segment_radius
    if radius is None:
        gap = tree.query(pos_a, k=2, workers=-1)[0][:, 1] if len(pos_a) > 1 else np.zeros(1)
        # a noisy scan's σ (30 cm for a ToF at 4.5 m) would join the whole scene: the σ term stops at 5 % of the
        # elements' extent, where the radius guard below would refuse a default it set itself
        extent = float(np.linalg.norm(np.ptp(pos_a, axis=0)))
        floor = max(3.0 * float(np.median(gap)), 1e-9)
        radius = max(floor, min(1.5 * float(np.median(sig_a)), 0.05 * extent))
        # 50 k changed points of a dense noisy scan at 5 % of a 4.6 m scene are 10⁸ pairs: a default the guard
        # below would refuse is narrowed to what it accepts (a radius the workflow sets is kept, and checked)
        radius = radius_within_pairs(tree, radius, floor)
    # a units mistake makes the radius span the whole data: refuse before the pair list takes all memory
    listed = check_radius(tree, radius, "fusion", "grouping changed elements into segments (`segment_radius`)")
    return radius_components(tree, radius, listed=listed)


def segments(items: list[CompositeItem], masks: dict[int, np.ndarray], kind: str, params: SegmentParams,
             start_id: int) -> list[Segment]:
    """Connected groups (radius graph) of the masked elements over all items."""
    stacked = _masked_elements(items, masks)
    if stacked is None:
        return []
    pos_a, owner_a, elem_a, score_a, sig_a = stacked
    label = segment_labels(pos_a, sig_a, params)
    order = np.argsort(label, kind="stable")
    bounds = np.flatnonzero(np.diff(label[order])) + 1
    out = []
    groups = sorted(np.split(order, bounds), key=lambda g: (-len(g), int(g.min())))  # largest first, stable ids
    for k, g in enumerate(groups):
        members = {items[i].key: np.sort(elem_a[g][owner_a[g] == i]) for i in np.unique(owner_a[g])}
        finite = score_a[g][np.isfinite(score_a[g])]
        out.append(Segment(id=start_id + k, kind=kind, centroid=pos_a[g].mean(axis=0), lower=pos_a[g].min(axis=0),
                           upper=pos_a[g].max(axis=0), mean_score=float(finite.mean()) if finite.size else float("nan"),
                           size=len(g), artefact=len(g) < params.min_segment_size, members=members))
    return out


def merged(parts: list[Segment], points: dict[int, np.ndarray]) -> Segment:
    """One segment of several (their members, positions and scores pooled) under the first one's id."""
    members: dict[str, list[np.ndarray]] = {}
    for g in parts:
        for key, idx in g.members.items():
            members.setdefault(key, []).append(idx)
    pts = np.vstack([points[g.id] for g in parts])
    sizes = np.array([g.size for g in parts], dtype=np.float64)
    scores = np.array([g.mean_score for g in parts])
    ok = np.isfinite(scores)
    mean_score = float(np.average(scores[ok], weights=sizes[ok])) if ok.any() else float("nan")
    return dataclasses.replace(parts[0], centroid=pts.mean(axis=0), lower=pts.min(axis=0), upper=pts.max(axis=0),
                               mean_score=mean_score, size=int(sizes.sum()), artefact=False,
                               members={k: np.sort(np.concatenate(v)) for k, v in members.items()})


def nearest_within(seed: Segment, others: list[Segment], reach: float) -> list[Segment]:
    """``seed`` and, nearest first, the other segments whose boxes keep the group's box diagonal within ``reach``."""
    group, lo, hi = [seed], seed.lower, seed.upper
    for h in sorted((h for h in others if h.id != seed.id),
                    key=lambda h: float(np.linalg.norm(h.centroid - seed.centroid))):
        lo2, hi2 = np.minimum(lo, h.lower), np.maximum(hi, h.upper)
        if np.linalg.norm(hi2 - lo2) <= reach:
            group.append(h)
            lo, hi = lo2, hi2
    return group
