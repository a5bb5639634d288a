"""Which chunks of a point file can hold points of a box: the file's chunks (runs of point records of a LAS/LAZ, the
octree nodes of a COPC) and the cells of a coarse grid each one touches, so that reading one tile of a large file
decompresses only the chunks that can hold its points, and numbers them as the whole read would.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# Cells along the longest side of the extent: 32³ cells at most, a few hundred kB of (chunk, cell) pairs for 10⁸
# points in 50 k-point chunks, while a box of a tenth of the extent still skips most chunks.
GRID_CELLS = 32


@dataclass(frozen=True)
class CellGrid:
    """A coarse grid over an extent; positions outside it fall in its edge cells (so a stale header extent costs
    selectivity, never a point)."""

    origin: np.ndarray
    size: float
    shape: tuple[int, int, int]

    @classmethod
    def over(cls, lower: np.ndarray, upper: np.ndarray, cells: int = GRID_CELLS) -> CellGrid:
        """The grid of ``cells`` cells along the longest side of [lower, upper]."""
        lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
        size = float(max(np.max(upper - lower), 1e-9)) / cells
        shape = np.clip(np.ceil((upper - lower) / size).astype(np.int64), 1, cells)
        return cls(lower, size, (int(shape[0]), int(shape[1]), int(shape[2])))

    def index3(self, positions: np.ndarray) -> np.ndarray:
        """(N,3) cell coordinates of positions, clipped to the grid."""
        top = np.asarray(self.shape) - 1
        cells: np.ndarray = np.clip(np.floor((positions - self.origin) / self.size).astype(np.int64), 0, top)
        return cells

    def flat(self, ijk: np.ndarray) -> np.ndarray:
        """Cell numbers of (N,3) cell coordinates."""
        nx, ny, _ = self.shape
        flat: np.ndarray = ijk[:, 0] + nx * (ijk[:, 1] + ny * ijk[:, 2])
        return flat

    def cells_in(self, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
        """Numbers of the cells the closed box [lower, upper] overlaps."""
        corners = self.index3(np.array([lower, upper], np.float64))
        lo, hi = corners[0], corners[1]
        axes = np.meshgrid(*(np.arange(a, b + 1) for a, b in zip(lo, hi, strict=True)), indexing="ij")
        return self.flat(np.column_stack([a.ravel() for a in axes]))


@dataclass(frozen=True)
class ChunkIndex:
    """Per chunk of a file, the cells its points touch; ``rows[c]`` and ``elements[c]`` are the first file row and the
    first element (point kept by the reader's filter) of chunk c, with the totals at the end."""

    grid: CellGrid
    rows: np.ndarray
    elements: np.ndarray
    pair_cells: np.ndarray  # sorted
    pair_chunks: np.ndarray  # the chunk of each pair
    lower: np.ndarray  # the kept points' extent
    upper: np.ndarray

    @classmethod
    def of(cls, grid: CellGrid, chunk_cells: Sequence[np.ndarray], rows: np.ndarray, kept: np.ndarray,
           lower: np.ndarray, upper: np.ndarray) -> ChunkIndex:
        """The index of chunks touching ``chunk_cells[c]`` (cell numbers), holding ``rows[c]`` records of which
        ``kept[c]`` pass the filter."""
        chunks = np.repeat(np.arange(len(chunk_cells)), [len(c) for c in chunk_cells])
        cells = np.concatenate(list(chunk_cells)) if len(chunk_cells) else np.zeros(0, np.int64)
        order = np.argsort(cells, kind="stable")
        return cls(grid, np.concatenate([[0], np.cumsum(rows, dtype=np.int64)]),
                   np.concatenate([[0], np.cumsum(kept, dtype=np.int64)]), cells[order], chunks[order],
                   np.asarray(lower, np.float64), np.asarray(upper, np.float64))

    @property
    def count(self) -> int:
        """How many elements the file holds after the filter."""
        return int(self.elements[-1])

    @property
    def n_chunks(self) -> int:
        """How many chunks the file has."""
        return len(self.rows) - 1

    def chunks(self, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
        """Sorted chunks that can hold points of the closed box [lower, upper]."""
        if np.any(np.asarray(upper) < self.lower) or np.any(np.asarray(lower) > self.upper):
            return np.zeros(0, np.int64)
        cells = self.grid.cells_in(lower, upper)
        starts = np.searchsorted(self.pair_cells, cells, side="left")
        ends = np.searchsorted(self.pair_cells, cells, side="right")
        hit = ends > starts
        if not hit.any():
            return np.zeros(0, np.int64)
        picked = np.concatenate([self.pair_chunks[s:e] for s, e in zip(starts[hit], ends[hit], strict=True)])
        return np.unique(picked)


class Indexed:
    """What a box source tells of itself from its index: how many elements, and their extent."""

    index: ChunkIndex

    @property
    def count(self) -> int:
        """Elements after the reader's filter."""
        return self.index.count

    @property
    def lower(self) -> np.ndarray:
        """The lower corner of the elements' extent."""
        return self.index.lower

    @property
    def upper(self) -> np.ndarray:
        """The upper corner of the elements' extent."""
        return self.index.upper


def runs(chunks: np.ndarray) -> list[tuple[int, int]]:
    """Sorted chunk numbers as runs [first, last + 1) of consecutive chunks (one seek and read each)."""
    if len(chunks) == 0:
        return []
    breaks = np.flatnonzero(np.diff(chunks) != 1) + 1
    firsts = chunks[np.concatenate([[0], breaks])]
    lasts = chunks[np.concatenate([breaks - 1, [len(chunks) - 1]])]
    return [(int(a), int(b) + 1) for a, b in zip(firsts, lasts, strict=True)]


def in_box(points: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Which points lie in the closed box [lower, upper] (the tiles' convention, ``tiling.CellIndex``)."""
    inside: np.ndarray = np.all((points >= lower) & (points <= upper), axis=1)
    return inside
