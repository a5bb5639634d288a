"""Points on a dataset's surface: its points, or area-weighted samples on its facets."""

from __future__ import annotations

import numpy as np

from ..types import Dataset


def sample_surface(ds: Dataset, spacing: float, rng: np.random.Generator, elements: np.ndarray | None = None
                   ) -> np.ndarray:
    """Points of a dataset: its points, or area-weighted samples on its facets (about one per spacing²)."""
    if ds.faces is None:
        return ds.points if elements is None else ds.points[elements]
    faces = ds.faces if elements is None else ds.faces[elements]
    tri = ds.points[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    counts = rng.poisson(area / spacing**2) + (area > 0)  # at least one per facet keeps small facets
    idx = np.repeat(np.arange(len(tri)), counts)
    r1, r2 = rng.random(len(idx)), rng.random(len(idx))
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    t = tri[idx]
    return t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])
