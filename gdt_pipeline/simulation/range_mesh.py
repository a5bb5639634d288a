"""A scan as the mesh a scanner's own software makes of it: neighbouring rays of the range image joined into
triangles, except across depth jumps (an object's silhouette against what lies behind it). Its vertices are the
measured points, so the mesh is exactly as precise as the scan, unlike a Poisson surface that smooths edges by
millimetres."""

from __future__ import annotations

import numpy as np

JUMP_PITCHES = 8.0  # a triangle spans at most this many ray pitches in range (surfaces up to ~83° of incidence)
JUMP_SIGMAS = 6.0  # plus this many σ of range noise


def range_image_mesh(scan) -> np.ndarray:  # scan: SimulatedScan with pixel and grid
    """Triangles (F,3) over the scan's points: two per 2 × 2 block of hit pixels, none across a depth jump, each
    facing the scanner."""
    rows, cols = scan.grid
    index = np.full(rows * cols, -1, dtype=np.int64)
    index[scan.pixel] = np.arange(len(scan.pixel))
    img = index.reshape(rows, cols)
    a, b, c, d = img[:-1, :-1].ravel(), img[:-1, 1:].ravel(), img[1:, :-1].ravel(), img[1:, 1:].ravel()
    tris = np.vstack([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
    tris = tris[np.all(tris >= 0, axis=1)]
    if not len(tris):
        return np.zeros((0, 3), dtype=np.int64)
    ranges = np.linalg.norm(scan.points - scan.viewpoint, axis=1)  # measured: the software knows no truth
    unit = (scan.points - scan.viewpoint) / ranges[:, None]
    # the angle between neighbouring rays, from the triangles' first edges
    pitch = float(np.median(np.linalg.norm(unit[tris[:, 0]] - unit[tris[:, 2]], axis=1)))
    r = ranges[tris]
    jump = JUMP_PITCHES * pitch * r.mean(axis=1) + JUMP_SIGMAS * scan.sigma_range[tris].max(axis=1)
    tris = tris[np.ptp(r, axis=1) <= jump]
    v = scan.points[tris]
    normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    away = np.einsum("ij,ij->i", normal, scan.viewpoint - v.mean(axis=1)) < 0
    tris[away] = tris[away][:, [0, 2, 1]]
    return tris
