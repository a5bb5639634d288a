"""Guards against a scale mistake turning a search quadratic: the recent data against the twin, and radius searches.

A scan written in millimetres but read as metres (a wrong ``units``) is 1000× the size of the CAD; a radius in twin
units that suits the CAD then holds every element of the scan, and an all-pairs search dies for lack of memory. These
checks are cheap (bounding boxes, a dual-tree count that builds no pair list) and name the likely cause instead.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..errors import StageError
from ..types import Composite, Dataset

MAX_SCALE_RATIO = 100.0  # recent vs reference bounding-box diagonal, either way
MAX_MEAN_NEIGHBOURS = 200  # per element, in a radius search that also spans a large part of the data
MIN_PAIRS_CHECKED = 1_000_000  # fewer pairs than this cost nothing, whatever their mean
MAX_RADIUS_SHARE = 0.1  # a radius over this share of the data's extent is at another scale than the data
MAX_PAIRS = 50_000_000  # a pair list of this size takes 800 MB: beyond it, refuse whatever the cause
MAX_SAMPLES = 20_000_000  # surface samples of one side of a registration


def diagonal(points: np.ndarray) -> float:
    """The bounding-box diagonal of ``points`` (0 for fewer than two)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 2:
        return 0.0
    return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))


def _visible_positions(reference: Composite) -> np.ndarray:
    parts = [it.dataset.element_positions()[it.visible] for it in reference.items if it.visible.any()]
    return np.vstack(parts) if parts else np.zeros((0, 3))


def check_scales(recent: Sequence[Dataset], reference: Composite | None, stage: str) -> None:
    """Refuse an epoch whose recent data's bounding box is over ``MAX_SCALE_RATIO`` times larger or smaller than the
    twin's (visible elements): almost always a wrong ``units``, which would make every later search meaningless."""
    if reference is None or not recent:
        return
    d_ref = diagonal(_visible_positions(reference))
    d_new = diagonal(np.vstack([ds.element_positions() for ds in recent]))
    if d_ref <= 0 or d_new <= 0:
        return
    ratio = d_new / d_ref
    if 1.0 / MAX_SCALE_RATIO <= ratio <= MAX_SCALE_RATIO:
        return
    names = ", ".join(ds.name for ds in recent)
    size = f"{ratio:,.0f}× the size" if ratio > 1 else f"1/{1 / ratio:,.0f} of the size"
    raise StageError(f"{stage}: the scan is {size} of the CAD (the recent data {names} spans a bounding-box "
                     f"diagonal of {d_new:.4g}, the twin {d_ref:.4g}, limit {MAX_SCALE_RATIO:g}× either way): check "
                     f"`units` of the inputs and of the workflow (a file in mm read as m is 1000× too large)")


def check_radius(tree: cKDTree, radius: float, stage: str, what: str) -> int | None:
    """Refuse a radius search at the wrong scale (over ``MAX_MEAN_NEIGHBOURS`` per element on average with a radius
    over ``MAX_RADIUS_SHARE`` of the data's extent) or too large for memory (over ``MAX_PAIRS`` pairs), before any
    pair list is built. Dense data with many neighbours at a radius that suits it passes (noisy scans do). Returns
    the ordered pairs it counted (each element with itself included), None when too few elements to count."""
    n = int(tree.n)
    if n < 2 or n * (n - 1) / 2 <= MIN_PAIRS_CHECKED:
        return None
    # a dual-tree count builds no list
    listed = int(tree.count_neighbors(tree, radius))
    pairs = (listed - n) / 2
    mean = 2.0 * pairs / n
    extent = diagonal(tree.data)
    wrong_scale = mean > MAX_MEAN_NEIGHBOURS and radius > MAX_RADIUS_SHARE * extent
    if pairs <= MIN_PAIRS_CHECKED or not (wrong_scale or pairs > MAX_PAIRS):
        return listed
    raise StageError(f"{stage}: {what} of radius {radius:.4g} would join {mean:.0f} of the {n} elements to each on "
                     f"average ({pairs:.3g} pairs; limits: {MAX_MEAN_NEIGHBOURS} on average with a radius over "
                     f"{MAX_RADIUS_SHARE:g} of the extent, {MAX_PAIRS:.0e} pairs in all); the data's extent "
                     f"(bounding-box diagonal) is {extent:.4g}, {extent / radius:.3g}× the radius. Likely cause: the "
                     f"data is not at the scale the radius assumes (check `units` of the inputs: a scan read in the "
                     f"wrong units is 1000× off), or the radius is set too large")


def radius_within_pairs(tree: cKDTree, radius: float, floor: float) -> float:
    """``radius``, or less (never under ``floor``) where a radius search at it would list over half ``MAX_PAIRS``
    pairs: a default radius is brought within what ``check_radius`` accepts rather than refused there."""
    n = int(tree.n)
    while radius > floor and (int(tree.count_neighbors(tree, radius)) - n) / 2 > MAX_PAIRS / 2:
        radius = max(0.7 * radius, floor)
    return radius


def expected_samples(ds: Dataset, spacing: float, elements: np.ndarray | None = None) -> float:
    """About how many points ``sample_surface`` returns for ``ds`` at ``spacing`` (its points, or area/spacing²)."""
    if ds.faces is None:
        return float(ds.n_elements if elements is None else len(elements))
    area = ds.facet_areas(elements)
    return float(area.sum() / spacing**2 + np.count_nonzero(area > 0))


def check_samples(count: float, spacing: float, stage: str, what: str) -> None:
    """Refuse sampling more than ``MAX_SAMPLES`` points: the spacing is far below the data's scale."""
    if count > MAX_SAMPLES:
        raise StageError(f"{stage}: sampling {what} at spacing {spacing:.4g} would take about {count:.3g} points "
                         f"(limit {MAX_SAMPLES:,}): the spacing (or the finest voxel) is far below the data's scale; "
                         f"check `units` of the inputs, or set `sample_spacing` / `voxels` to suit the data")
