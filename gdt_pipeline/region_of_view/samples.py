"""Reference elements as samples spread over their area, so that a facet is judged on all of it, not on its middle:
a facet is cut into m² equal sub-triangles (m from its area and the recent data's spacing, up to a cap) and sampled
at their centroids; a point is its own sample."""

from __future__ import annotations

from functools import cache

import numpy as np

from ..types import Dataset


@cache
def sub_centroids(m: int) -> np.ndarray:
    """Barycentric coordinates (m², 3) of the centroids of the m² equal triangles a triangle splits into."""
    out = []
    for i in range(m):
        for j in range(m - i):
            out.append(((i + 1 / 3) / m, (j + 1 / 3) / m))  # the upward triangle at (i, j)
            if i + j <= m - 2:
                out.append(((i + 2 / 3) / m, (j + 2 / 3) / m))  # the downward one beside it
    uv = np.array(out)
    return np.column_stack([1 - uv.sum(axis=1), uv])


def area_samples(ds: Dataset, spacing: float, cap: int, single: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Sample positions and the element each belongs to: about one per spacing² of each facet (at most ``cap``,
    at least one; exactly one for the facets ``single`` marks), or the points themselves."""
    if ds.faces is None:
        return np.asarray(ds.points), np.arange(len(ds.points))
    tri = ds.points[ds.faces]
    area = ds.facet_areas()
    per_side = np.clip(np.ceil(np.sqrt(area / max(spacing, 1e-12) ** 2)), 1, max(1, int(np.sqrt(cap))))
    per_side = per_side.astype(np.int64)
    if single is not None:
        per_side[single] = 1
    pos, owner = [], []
    for m in np.unique(per_side):  # a loop over the few subdivision levels; facets are vectorised
        idx = np.flatnonzero(per_side == m)
        bary = sub_centroids(int(m))
        pos.append(np.einsum("sk,fkj->fsj", bary, tri[idx]).reshape(-1, 3))
        owner.append(np.repeat(idx, len(bary)))
    return np.vstack(pos), np.concatenate(owner)
