"""Triangle arithmetic that datasets, samplers and readers share: normals, areas and points at random places."""
from __future__ import annotations

import numpy as np


def triangle_normals(tri: np.ndarray) -> np.ndarray:
    """Normals of triangles ``(F,3,3)`` by the right-hand rule, twice each triangle's area long."""
    return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def triangle_areas(tri: np.ndarray) -> np.ndarray:
    """Areas of triangles ``(F,3,3)``."""
    return np.asarray(0.5 * np.linalg.norm(triangle_normals(tri), axis=1))


def triangle_points(tri: np.ndarray, facet: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Points on the triangles ``tri[facet]`` from two uniforms in [0, 1) each: the unit square folded onto the
    triangle, so that points are uniform over its area (``u`` and ``v`` are folded in place)."""
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[facet]
    return np.asarray(t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0]))
