"""Which elements of a large set lie in a box, without scanning the whole set once per tile: positions bucketed by
the tile grid's cells once, then a box query visits only the cells it overlaps."""

from __future__ import annotations

import numpy as np

from ..types.arrays import index_dtype
from .grid import TileGrid


class CellIndex:
    """Positions sorted by grid cell; ``query(lower, upper)`` returns the sorted indices of those inside the box."""

    def __init__(self, grid: TileGrid, positions: np.ndarray) -> None:
        self.grid = grid
        self.positions = positions
        cells = grid.cell(positions)
        self.order = np.argsort(cells, kind="stable").astype(index_dtype(len(positions)))
        self.sorted_cells = cells[self.order]

    def query(self, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
        """Sorted indices of the positions inside the closed box [lower, upper]."""
        g = self.grid
        top = np.asarray(g.shape) - 1
        lo = np.clip(np.floor((lower - g.origin) / g.size).astype(np.int64), 0, top)
        hi = np.clip(np.floor((upper - g.origin) / g.size).astype(np.int64), 0, top)
        ii, jj, kk = np.meshgrid(*(np.arange(a, b + 1) for a, b in zip(lo, hi, strict=True)), indexing="ij")
        cells = (ii + g.shape[0] * (jj + g.shape[1] * kk)).ravel()
        starts = np.searchsorted(self.sorted_cells, cells, side="left")
        ends = np.searchsorted(self.sorted_cells, cells, side="right")
        if not np.any(ends > starts):
            return np.zeros(0, dtype=self.order.dtype)
        cand = np.concatenate([self.order[s:e] for s, e in zip(starts, ends, strict=True) if e > s])
        p = self.positions[cand]
        inside = np.all((p >= lower) & (p <= upper), axis=1)
        return np.sort(cand[inside])
