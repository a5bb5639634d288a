"""Visibility from per-station depth images of the recent data: a reference sample is *present* when a station
measured a surface at its depth (within k σ along the ray), *through* when the station saw past its place (measured
surface clearly behind it, or nothing within a pose file's range), *hidden* when measured surface stands clearly in
front of it. No surface is reconstructed: the cost is a sort of the points and a few binary searches per sample.

A depth image is not a pixel array: its pixels are keys of an angular grid around the station (azimuth and elevation
in a frame looking at the station's data, the pixel a little wider than the points' angular spacing), and the points
are sorted by (pixel, range). A sample's 3 × 3 window of pixels then gives, by binary search, how many points lie in
front of, at and behind its depth.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

NONE, HIDDEN, THROUGH, PRESENT = 0, 1, 2, 3  # ordered: where stations disagree, the larger code wins
ROW = np.int64(1) << np.int64(32)  # key = row · 2³² + column; columns stay within ±2³¹ for pixels over 1.5 nrad
MAX_COS_GRAZING = np.cos(np.radians(85.0))  # facets seen at over 85° of incidence are not judged from that station
WINDOW_REACH = 2.0  # pixels: the farthest a point of the 3 × 3 window lies from the sample, across the beam


def view_frame(fwd: np.ndarray) -> np.ndarray:
    """Rows: the view axis along ``fwd``, the right and the up direction of a sensor looking along it."""
    fwd = fwd / np.linalg.norm(fwd)
    helper = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.95 else np.array([1.0, 0.0, 0.0])
    right = np.cross(fwd, helper)
    right /= np.linalg.norm(right)
    return np.vstack([fwd, right, np.cross(right, fwd)])


@dataclass(frozen=True)
class Station:
    """One sensor position, the recent datasets it measured, and what is known of its rays."""

    eye: np.ndarray
    contains: Callable[[np.ndarray], np.ndarray]  # which points its own volume holds
    datasets: tuple[int, ...]  # indices of the recent datasets it measured
    free_range: float = 0.0  # a pose file's range: nothing measured closer than this means empty space; 0: unknown


@dataclass(frozen=True)
class DepthImage:
    """A station's measured points sorted by angular pixel and range (see the module docstring)."""

    eye: np.ndarray
    frame: np.ndarray
    pixel: float  # rad
    keys: np.ndarray  # the occupied pixels' keys, sorted
    sigma: np.ndarray  # per occupied pixel, the mean σ of its points along the ray
    ranked: np.ndarray  # per point, its pixel's rank + range / scale, sorted
    scale: float
    free_range: float


def angles(frame: np.ndarray, eye: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Azimuth and elevation of each point in the station's frame, and its range."""
    d = pts - eye
    rng = np.linalg.norm(d, axis=1)
    local = d @ frame.T
    el = np.arcsin(np.clip(local[:, 2] / np.maximum(rng, 1e-300), -1.0, 1.0))
    return np.arctan2(local[:, 1], local[:, 0]), el, rng


def pixel_keys(az: np.ndarray, el: np.ndarray, pixel: float, drow: int = 0, dcol: int = 0) -> np.ndarray:
    """The key of the pixel ``drow`` rows and ``dcol`` columns from each direction's own."""
    row = np.floor(el / pixel).astype(np.int64) + drow
    # columns are as wide in true angle on every row: a row's azimuth step grows as 1 / cos(elevation)
    col = np.floor(az * np.maximum(np.cos((row + 0.5) * pixel), 1e-3) / pixel).astype(np.int64) + dcol
    return row * ROW + col


def angular_spacing(az: np.ndarray, el: np.ndarray) -> float:
    """The median angular distance from a point to its nearest neighbour (on at most about 20000 of them)."""
    xy = np.column_stack([az * np.cos(el), el])
    sample = xy[:: max(1, len(xy) // 20000)]
    d, _ = cKDTree(xy).query(sample, k=2)
    return float(np.median(d[:, 1]))


def along(cov: np.ndarray, unit: np.ndarray) -> np.ndarray:
    """σ along each unit direction of each (3,3) covariance (or one covariance for all)."""
    if cov.ndim == 2:
        return np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", unit, cov, unit), 0.0))
    return np.sqrt(np.maximum(np.einsum("ij,ijk,ik->i", unit, cov, unit), 0.0))


def build_image(station: Station, pts: np.ndarray, cov: np.ndarray, pixel_scale: float) -> DepthImage | None:
    """The station's depth image of its measured points with their covariances (None without points)."""
    if len(pts) < 2:
        return None
    frame = view_frame((pts - station.eye).mean(axis=0))
    az, el, rng = angles(frame, station.eye, pts)
    pixel = pixel_scale * max(angular_spacing(az, el), 1e-8)
    key = pixel_keys(az, el, pixel)
    sig = along(cov, (pts - station.eye) / np.maximum(rng, 1e-300)[:, None])
    order = np.lexsort((rng, key))
    key, rng, sig = key[order], rng[order], sig[order]
    keys, start, counts = np.unique(key, return_index=True, return_counts=True)
    scale = float(rng.max()) * 1.01 + 1e-9
    ranked = np.repeat(np.arange(len(keys), dtype=np.float64), counts) + rng / scale
    return DepthImage(eye=station.eye, frame=frame, pixel=pixel, keys=keys,
                      sigma=np.add.reduceat(sig, start) / counts, ranked=ranked, scale=scale,
                      free_range=station.free_range)


def classify(img: DepthImage, pos: np.ndarray, cov: np.ndarray, normals: np.ndarray | None, k: float) -> np.ndarray:
    """Per sample (position, covariance, facet normal), what the station saw at its place: NONE, HIDDEN, THROUGH
    or PRESENT (counts of points in front of, at and behind its depth over its 3 × 3 window)."""
    az, el, depth = angles(img.frame, img.eye, pos)
    unit = (pos - img.eye) / np.maximum(depth, 1e-300)[:, None]
    sig_e = along(cov, unit)
    # a tilted surface's depth changes across the window: allow for it over the window's reach
    slope = np.zeros(len(pos))
    judged = np.ones(len(pos), dtype=bool)
    if normals is not None:
        cos = np.abs(np.einsum("ij,ij->i", normals, unit)) / np.maximum(np.linalg.norm(normals, axis=1), 1e-300)
        judged = cos > MAX_COS_GRAZING
        slope = np.sqrt(np.maximum(1 - cos**2, 0)) / np.maximum(cos, MAX_COS_GRAZING)
    reach = WINDOW_REACH * img.pixel * depth * slope
    counts = np.zeros((3, len(pos)), dtype=np.int64)  # front, at, behind
    for drow in (-1, 0, 1):
        for dcol in (-1, 0, 1):
            key = pixel_keys(az, el, img.pixel, drow, dcol)
            rank = np.minimum(np.searchsorted(img.keys, key), len(img.keys) - 1)
            hit = np.flatnonzero(img.keys[rank] == key)
            r = rank[hit].astype(np.float64)
            tol = k * np.sqrt(img.sigma[rank[hit]] ** 2 + sig_e[hit] ** 2) + reach[hit]
            lo = r + np.clip((depth[hit] - tol) / img.scale, 0, 1)
            hi = r + np.clip((depth[hit] + tol) / img.scale, 0, 1)
            edges = np.vstack([np.searchsorted(img.ranked, r), np.searchsorted(img.ranked, lo),
                               np.searchsorted(img.ranked, hi, side="right"), np.searchsorted(img.ranked, r + 1)])
            counts[:, hit] += np.diff(edges, axis=0)
    front, at, behind = counts
    code = np.where(at > 0, PRESENT, np.where(front > 0, HIDDEN, np.where(behind > 0, THROUGH, NONE)))
    empty = (front + at + behind == 0) & (depth < img.free_range)
    return np.where(judged, np.where(empty, THROUGH, code), NONE).astype(np.int8)
