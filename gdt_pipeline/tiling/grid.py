"""The 3-D tile grid: cubes of one size over the recent data's bounding box; each recent element belongs to the core
of exactly one tile (the cube its position falls in, lower faces closed, upper faces open)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..types.arrays import index_dtype

# Tile sizes from a budget are halved from the whole extent until the fullest tile fits; below this many cells per
# axis a finer grid is not tried (a tile that thin is all halo).
MAX_SPLITS = 12
CELL_CHUNK = 1 << 20  # positions whose cells are found at once


@dataclass(frozen=True)
class TileGrid:
    """Cubes of edge ``size`` from ``origin``, ``shape`` of them along x, y, z; tiles are numbered x-fastest."""

    origin: np.ndarray
    size: float
    shape: tuple[int, int, int]

    def cell(self, positions: np.ndarray) -> np.ndarray:
        """The tile number of each position (positions outside the grid go to the nearest border tile), in the
        narrowest of int32 and int64 that holds every tile's number."""
        out = np.empty(len(positions), dtype=index_dtype(self.count))
        for c0 in range(0, len(positions), CELL_CHUNK):  # 48 B a position of temporaries, a chunk at a time
            part = np.asarray(positions[c0:c0 + CELL_CHUNK], dtype=np.float64)
            ijk = np.floor((part - self.origin) / self.size).astype(np.int64)
            ijk = np.clip(ijk, 0, np.asarray(self.shape) - 1)
            out[c0:c0 + CELL_CHUNK] = ijk[:, 0] + self.shape[0] * (ijk[:, 1] + self.shape[1] * ijk[:, 2])
        return out

    def bounds(self, tile: int) -> tuple[np.ndarray, np.ndarray]:
        """The lower and upper corner of tile ``tile``'s core."""
        nx, ny, _ = self.shape
        ijk = np.array([tile % nx, (tile // nx) % ny, tile // (nx * ny)], dtype=np.float64)
        lower = self.origin + ijk * self.size
        return lower, lower + self.size

    @property
    def count(self) -> int:
        """Number of tiles in the grid (empty ones included)."""
        return int(np.prod(self.shape))


def extent(positions: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corner of all positions (a unit box at the origin when there are none)."""
    parts = [p for p in positions if len(p)]
    if not parts:
        return np.zeros(3), np.ones(3)
    return (np.min([p.min(axis=0) for p in parts], axis=0), np.max([p.max(axis=0) for p in parts], axis=0))


def grid_for(positions: Sequence[np.ndarray], size: float) -> TileGrid:
    """The grid of cubes of edge ``size`` that covers every position."""
    if not size > 0:
        raise ValueError(f"tile size must be > 0, got {size}")
    lower, upper = extent(positions)
    shape = np.maximum(np.ceil((upper - lower) / size).astype(np.int64), 1)
    # a position exactly on the upper face belongs to the last tile (cell() clips it there)
    return TileGrid(origin=lower, size=float(size), shape=(int(shape[0]), int(shape[1]), int(shape[2])))


def size_for_budget(positions: Sequence[np.ndarray], max_elements: int) -> float:
    """The largest tile size (the extent halved k times) whose fullest tile holds at most ``max_elements`` elements."""
    lower, upper = extent(positions)
    size = float(np.max(upper - lower)) * (1 + 1e-9)
    for _ in range(MAX_SPLITS):
        grid = grid_for(positions, size)
        fullest = np.bincount(np.concatenate([grid.cell(p) for p in positions]), minlength=grid.count).max()
        if fullest <= max_elements:
            return size
        size /= 2
    return size
