"""Defaults scaled to the data: when a workflow gives no ``voxels``, the coarse-to-fine ICP schedule comes from the
clouds' own point spacing (median nearest-neighbour distance of a sample) and extent (bounding-box diagonal).

The fixed 5/2/1 cm of earlier releases suit a 5 mm-spaced scan of a part; on airborne LiDAR with 3 m spacing they
leave almost no point with a correspondence (fitness 6e-5 on the Toronto pair). The factors below reproduce those
centimetres on the simulated 5.4 mm scans (10, 4 and 2 spacings: 5.4, 2.1, 1.1 cm) and scale with the data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from gdt_pipeline import StageError

SPACING_FACTORS = (10.0, 4.0, 2.0)  # voxels of the schedule, in point spacings, coarse to fine
MAX_COARSE_SHARE = 0.05  # the coarsest voxel at most this share of the bounding-box diagonal
SPACING_SAMPLE = 5000  # points whose nearest neighbour is searched (a deterministic stride, no draw)
MESH_SHARE = 1.0 / 500  # spacing of a mesh-only registration, as a share of its diagonal


@dataclass(frozen=True)
class Schedule:
    """The voxel sizes, correspondence distances and mesh sample spacing one registration runs with."""

    voxels: tuple[float, ...]
    max_distance_factor: float
    sample_spacing: float
    spacing: float | None  # the data's median point spacing when the schedule was derived from it
    derived: bool

    @property
    def final_distance(self) -> float:
        """The correspondence distance of the finest level."""
        return self.voxels[-1] * self.max_distance_factor

    def record(self) -> dict[str, object]:
        """The schedule as the stage reports it (into the provenance)."""
        return {"voxels": list(self.voxels), "max_distances": [v * self.max_distance_factor for v in self.voxels],
                "sample_spacing": self.sample_spacing, "point_spacing": self.spacing, "derived": self.derived}


def point_spacing(points: np.ndarray) -> float:
    """Median distance from a stride sample of ``points`` to its nearest other point (0 for fewer than two)."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        return 0.0
    sample = pts[:: max(1, len(pts) // SPACING_SAMPLE)]
    d, _ = cKDTree(pts).query(sample, k=2, workers=-1)
    positive = d[:, 1][d[:, 1] > 0]  # duplicated points say nothing of the spacing
    return float(np.median(positive)) if len(positive) else 0.0


def schedule_for(params: Any, point_sets: list[np.ndarray], diagonal: float, method: str) -> Schedule:
    """The schedule of ``params`` (a ``ScheduleParams``): its own voxels when given, else scaled to the spacing of
    ``point_sets`` (the sparser side's; the data's ``diagonal`` / 500 when both sides are meshes) and to the
    ``diagonal`` of the recent data."""
    voxels, factor, given_spacing = params.voxels, float(params.max_distance_factor), params.sample_spacing
    if voxels:
        vox = tuple(float(v) for v in voxels)
        return Schedule(vox, factor, float(given_spacing or vox[-1] / 2), None, False)
    sets = [s for s in point_sets if len(s) >= 2]
    spacing = max(point_spacing(s) for s in sets) if sets else diagonal * MESH_SHARE
    if not np.isfinite(spacing) or spacing <= 0:
        raise StageError(f"{method}: cannot derive a voxel schedule: the data's point spacing is {spacing:g} (all "
                         f"points coincide?); give `voxels` explicitly")
    vox = [f * spacing for f in SPACING_FACTORS]
    cap = MAX_COARSE_SHARE * diagonal
    if diagonal > 0 and vox[0] > cap:  # a small scene: keep the coarse level inside it, never below the finest
        vox[0] = max(cap, vox[-1])
        vox[1] = min(vox[1], vox[0])
    return Schedule(tuple(vox), factor, float(given_spacing or vox[-1] / 2), spacing, True)
