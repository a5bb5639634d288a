"""Points on a dataset's surface: its points, or area-weighted samples on its facets."""

from __future__ import annotations

import numpy as np

from ..types import Dataset
from ..types.triangles import triangle_areas, triangle_points


def sample_surface(ds: Dataset, spacing: float, rng: np.random.Generator, elements: np.ndarray | None = None
                   ) -> np.ndarray:
    """Points of a dataset: its points, or area-weighted samples on its facets (about one per spacing²)."""
    if ds.faces is None:
        return ds.points if elements is None else ds.points[elements]
    tri = ds.points[ds.faces if elements is None else ds.faces[elements]]
    area = triangle_areas(tri)
    counts = rng.poisson(area / spacing**2) + (area > 0)  # at least one per facet keeps small facets
    idx = np.repeat(np.arange(len(tri)), counts)
    r1, r2 = rng.random(len(idx)), rng.random(len(idx))
    return triangle_points(tri, idx, r1, r2)
