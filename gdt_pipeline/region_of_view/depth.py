"""Visibility from per-station depth images of the recent data: a reference sample is *present* when a station
measured surface on its plane (within k σ along the facet's normal, the point's and the element's), *seen through*
when the station measured surface clearly behind it (or nothing at all within a pose file's range), *hidden* when
measured surface stands clearly in front of it. No surface is reconstructed: the cost is a sort of the points and a
few binary searches per sample.

A depth image is not a pixel array: its pixels are keys of an angular grid around the station (azimuth and elevation
in a frame looking at the station's data, the pixel the angle between its neighbouring rays), and the points are sorted
by pixel. A sample's 3 × 3 window of pixels then gives, by binary search, the points that may lie at its place; each
is placed against the sample's plane by its signed distance along the normal, where a precise scanner's σ holds even
at oblique incidence (along the ray, a 5 mm step on a face seen at 80° would hide in 3 cm of depth per pixel), and
the plurality of the window's points (in front, on the plane, behind) decides.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..memory import release_scratch_pages
from ..types.arrays import index_dtype
from .window_kernel import window_sides

NONE, HIDDEN, THROUGH, PRESENT = 0, 1, 2, 3  # what the stations together say of a sample
ROW = np.int64(1) << np.int64(32)  # key = row · 2³² + column; columns stay within ±2³¹ for pixels over 1.5 nrad
MAX_COS_GRAZING = np.cos(np.radians(85.0))  # facets seen at over 85° of incidence are not judged from that station
CHUNK = 200_000  # samples classified at once: bounds the chunk's temporaries
FOOTPRINT = 0.6  # pixels: a ray passing this close to a facet still tells what is at its edge


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
    """A station's measured points sorted by angular pixel (see the module docstring). The points and covariances
    are the datasets' own arrays, not sorted copies (72 B a point of the epoch): ``order`` lists them by pixel."""

    eye: np.ndarray
    frame: np.ndarray
    pixel: float  # rad
    keys: np.ndarray  # the occupied pixels' keys, sorted
    bounds: np.ndarray  # (P+1,): pixel i's points are order[bounds[i]:bounds[i + 1]]
    order: np.ndarray  # (N,) the rows of ``points`` and ``cov`` by pixel
    points: np.ndarray  # (N,3) as measured
    cov: np.ndarray  # (N,3,3) their covariances (a shared one broadcast)
    free_range: float


def angles(frame: np.ndarray, eye: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Azimuth and elevation of each point in the station's frame, and its range."""
    d = pts - eye
    rng = np.linalg.norm(d, axis=1)
    local = d @ frame.T
    el = np.arcsin(np.clip(local[:, 2] / np.maximum(rng, 1e-300), -1.0, 1.0))
    return np.arctan2(local[:, 1], local[:, 0]), el, rng


def pixel_cells(az: np.ndarray, el: np.ndarray, pixel: float, drow: int = 0, dcol: int = 0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixel ``drow`` rows and ``dcol`` columns from each direction's own: its key, and the azimuth and
    elevation of its centre."""
    row = np.floor(el / pixel).astype(np.int64) + drow
    # columns are as wide in true angle on every row: a row's azimuth step grows as 1 / cos(elevation)
    row_cos = np.maximum(np.cos((row + 0.5) * pixel), 1e-3)
    col = np.floor(az * row_cos / pixel).astype(np.int64) + dcol
    return row * ROW + col, (col + 0.5) * pixel / row_cos, (row + 0.5) * pixel


def pixel_keys(az: np.ndarray, el: np.ndarray, pixel: float) -> np.ndarray:
    """The key of each direction's pixel."""
    return pixel_cells(az, el, pixel)[0]


def angular_spacing(az: np.ndarray, el: np.ndarray) -> float:
    """The median angular distance from a point to its nearest neighbour (on at most about 20000 of them)."""
    xy = np.column_stack([az * np.cos(el), el])
    sample = xy[:: max(1, len(xy) // 20000)]
    d, _ = cKDTree(xy).query(sample, k=2, workers=-1)
    return float(np.median(d[:, 1]))


def ray_pitch(az: np.ndarray, el: np.ndarray) -> float:
    """The angle between a station's neighbouring rays: the square root of the solid angle its points cover (cells
    of four nearest-neighbour spacings that hold a point) per point. Not the nearest-neighbour spacing itself, which
    lateral noise shrinks well below the scanner's pitch (a ToF at 4.5 m: 0.8 against 3 mrad)."""
    nearest = max(angular_spacing(az, el), 1e-8)
    cell = 4.0 * nearest
    covered = np.unique(pixel_keys(az, el, cell)).size * cell**2
    return max(float(np.sqrt(covered / len(az))), nearest)


def build_image(station: Station, pts: np.ndarray, cov: np.ndarray, pixel_scale: float) -> DepthImage | None:
    """The station's depth image of its measured points and their (N,3,3) covariances, both kept as given (None
    without points)."""
    if len(pts) < 2:
        return None
    frame = view_frame((pts - station.eye).mean(axis=0))
    az, el, _ = angles(frame, station.eye, pts)
    pixel = pixel_scale * ray_pitch(az, el)
    key = pixel_keys(az, el, pixel)
    del az, el
    order = np.argsort(key, kind="stable")
    key = key[order]
    first = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    index = index_dtype(len(pts))
    return DepthImage(eye=station.eye, frame=frame, pixel=pixel, keys=key[first],
                      bounds=np.append(first, len(key)).astype(index), order=order.astype(index),
                      points=np.asarray(pts), cov=np.asarray(cov), free_range=station.free_range)


def window_votes(img: DepthImage, pos: np.ndarray, cov: np.ndarray, tris: np.ndarray | None, k: float,
                 owner: np.ndarray | None = None) -> np.ndarray:
    """Per sample (position, covariance, the (3,3) corners of its facet or None for points), what this station
    says of its place, as votes (2, M): points at it and points behind it (an empty window within a pose file's
    range is one vote behind); none where the station's points mostly stand in front of it (hidden from it).

    With ``owner``, ``cov`` and ``tris`` are per element and each sample takes its owner's, gathered a chunk at a
    time (a million samples' covariances and corners are 144 MB)."""
    out = np.zeros((2, len(pos)), dtype=np.int32)
    for s0 in range(0, len(pos), CHUNK):
        part = slice(s0, s0 + CHUNK)
        rows = part if owner is None else owner[part]
        out[:, part] = votes_chunk(img, pos[part], cov[rows], None if tris is None else tris[rows], k)
        release_scratch_pages()  # the image's covariances, read at random, may be a scratch file's rows
    return out


def votes_chunk(img: DepthImage, pos: np.ndarray, cov: np.ndarray, tris: np.ndarray | None, k: float
                ) -> np.ndarray:
    """``window_votes`` on one chunk of samples: the points of each sample's 3 × 3 window whose rays pass through
    its facet (within FOOTPRINT pixels of it; all of them for a point sample), placed against its plane (a point
    sample's plane faces the station): in front of it, at it, or behind it."""
    az, el, depth = angles(img.frame, img.eye, pos)
    normals, judged = facing_normals(img.eye, pos, depth, tris)
    var_e = np.einsum("ij,ijk,ik->i", normals, cov, normals)
    counts = np.zeros((3, len(pos)), dtype=np.int32)  # front, at, behind
    pooled = np.zeros((2, len(pos)))  # over the points not in front: sum of offsets, sum of their variances
    cells = np.column_stack([pixel_cells(az, el, img.pixel, drow, dcol)[0] for drow in (-1, 0, 1)
                             for dcol in (-1, 0, 1)])
    # only rays through the facet say what is at its place: a neighbour's surface beside a thin face, or one
    # crossing a removed face's plane, is not the face (window_kernel: the test, per sample and window cell)
    window_sides(cells, judged, pos, normals, np.zeros((0, 3, 3)) if tris is None else np.ascontiguousarray(tris),
                 FOOTPRINT * img.pixel * depth, var_e, img.eye, img.keys, img.bounds, img.order, img.points,
                 img.cov, k, counts, pooled)
    front, at, behind = counts
    # each point within k σ of the plane, their mean clearly behind it: a surface a noisy scanner measured a few
    # σ behind a removed part's place (the floor under a pipe, 5 cm below at σ 3 cm) is not the part
    n = at + behind
    mean = pooled[0] / np.maximum(n, 1)
    behind_all = (n >= 2) & (mean < -k * np.sqrt(pooled[1] / np.maximum(n, 1) ** 2 + var_e))
    at, behind = np.where(behind_all, 0, at), np.where(behind_all, n, behind)
    hidden = (front > at) & (front >= behind)
    empty = judged & (front + at + behind == 0) & (depth < img.free_range)
    return np.vstack([np.where(hidden, 0, at), np.where(hidden, 0, behind) + empty])


def facing_normals(eye: np.ndarray, pos: np.ndarray, depth: np.ndarray, tris: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Per sample, the unit normal of its plane on the side the station sees (towards the station for a point), and
    whether it is seen at under 85° of incidence."""
    toward = (eye - pos) / np.maximum(depth, 1e-300)[:, None]
    if tris is None:
        return toward, np.ones(len(pos), dtype=bool)
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    facing = np.einsum("ij,ij->i", normals, toward)
    return np.where(facing[:, None] < 0, -normals, normals), np.abs(facing) > MAX_COS_GRAZING
