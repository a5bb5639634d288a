"""Binary PLY point clouds read one box at a time (``ReaderSpec.boxes``): a first pass over the vertex rows, a run
of rows at a time, checks them as the whole read does (finite coordinates, the file's length) and records which
coarse-grid cells each run touches; a box then reads only the runs that touch its cells.

Rows are read with ``np.fromfile`` rather than a memory map: a map's touched pages stay in the process's resident
set, so a pass over a 1 GB map would show (and hold, until the kernel wants them back) 1 GB.
"""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import numpy as np

from gdt_pipeline import BoxRead, InputError

from .cell_cache import CellCache
from .chunk_index import CellGrid, ChunkIndex, Indexed, in_box, runs
from .ply import row_dtype
from .ply_header import read_header

# Vertex rows per run (a few MB of rows; a box reads whole runs).
PLY_RUN = 65_536


class PlyBoxes(Indexed):
    """A binary PLY whose rows are all vertices of one fixed size (a point cloud), indexed by a first pass; with
    ``sort_cells``, its points sorted by cell into a scratch file under ``scratch``, which box reads then read."""

    def __init__(self, path: Path, sort_cells: bool = False, scratch: Path | None = None) -> None:
        self.path = path
        header = read_header(path)
        if not header.endian or [el.name for el in header.elements] != ["vertex"] or not header.elements[0].fixed:
            raise InputError(f"{path}: box reads need a binary PLY of fixed-size vertex rows only (this one is "
                             f"{header.fmt} with elements {[el.name for el in header.elements]})")
        vertex = header.elements[0]
        self.row = row_dtype(vertex.props, header.endian, {})
        missing = [c for c in "xyz" if c not in self.row.names]
        if missing:
            raise InputError(f"{path}: element 'vertex' has no property {', '.join(missing)}")
        self.offset, self.total = header.body_offset, vertex.count
        size = path.stat().st_size
        if self.offset + self.total * self.row.itemsize != size:
            raise InputError(f"{path}: element 'vertex' declares {self.total} rows of {self.row.itemsize} bytes from "
                             f"byte {self.offset}, but the file is {size} bytes: the header's count does not describe "
                             f"the data")
        self.file: BinaryIO = open(path, "rb")  # noqa: SIM115 - held for the box reads, closed by close()
        self.cache: CellCache | None = None
        self.index = self._indexed()
        if sort_cells:
            self.cache = self._sorted(scratch)

    def _xyz(self, first_row: int, rows: int) -> np.ndarray:
        self.file.seek(self.offset + first_row * self.row.itemsize)
        data = np.fromfile(self.file, dtype=self.row, count=rows)
        if len(data) != rows:
            raise InputError(f"{self.path}: {len(data)} vertex rows from row {first_row}, {rows} expected (was the "
                             f"file changed while being read?)")
        return np.column_stack([np.asarray(data[c], np.float64) for c in "xyz"])

    def _indexed(self) -> ChunkIndex:
        """The first pass, reading the rows twice: their extent, then the cells each run touches."""
        n_runs = max(1, -(-self.total // PLY_RUN))
        lower, upper = np.full(3, np.inf), np.full(3, -np.inf)
        for k in range(n_runs):
            xyz = self._xyz(k * PLY_RUN, min(PLY_RUN, self.total - k * PLY_RUN))
            bad = ~np.isfinite(xyz).all(axis=1)
            if bad.any():
                row = k * PLY_RUN + int(np.argmax(bad))
                raise InputError(f"{self.path}: vertex row {row} (counting from 0; byte offset "
                                 f"{self.offset + row * self.row.itemsize}) is NaN or infinite: "
                                 f"{xyz[row - k * PLY_RUN].tolist()} ({int(bad.sum())} such rows among rows "
                                 f"{k * PLY_RUN}-{k * PLY_RUN + len(xyz) - 1})")
            if len(xyz):
                lower, upper = np.minimum(lower, xyz.min(axis=0)), np.maximum(upper, xyz.max(axis=0))
        if not np.all(np.isfinite(lower)):
            lower = upper = np.zeros(3)
        grid = CellGrid.over(lower, upper)
        self.cell_totals = np.zeros(int(np.prod(grid.shape)), np.int64)
        cells = []
        for k in range(n_runs):
            point_cells = grid.flat(grid.index3(self._xyz(k * PLY_RUN, min(PLY_RUN, self.total - k * PLY_RUN))))
            self.cell_totals += np.bincount(point_cells, minlength=len(self.cell_totals))
            cells.append(np.unique(point_cells))
        rows = np.array([min(PLY_RUN, self.total - k * PLY_RUN) for k in range(n_runs)], np.int64)
        return ChunkIndex.of(grid, cells, rows, rows, lower, upper)

    def _sorted(self, scratch: Path | None) -> CellCache:
        """A third read of the rows: each into its cell's rows of a scratch file."""
        try:
            cache = CellCache(self.index.grid, self.cell_totals, {}, scratch)
        except InputError as exc:
            self.file.close()
            raise InputError(f"{self.path}: {exc}") from exc
        try:
            for row in range(0, self.total, PLY_RUN):
                n = min(PLY_RUN, self.total - row)
                cache.write(row + np.arange(n), self._xyz(row, n), {})
            cache.check_full()
        except BaseException as exc:
            cache.close()
            self.file.close()
            if isinstance(exc, InputError) and str(self.path) not in str(exc):
                raise InputError(f"{self.path}: {exc}") from exc
            raise
        return cache

    def read_box(self, lower: np.ndarray, upper: np.ndarray) -> BoxRead:
        """The vertices inside the closed box [lower, upper], numbered by their row."""
        lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
        if self.cache is not None:
            elements, xyz, _ = self.cache.read(lower, upper)
            return BoxRead(elements, xyz)
        numbers, points = [], []
        for first, last in runs(self.index.chunks(lower, upper)):
            start = int(self.index.rows[first])
            for row in range(start, int(self.index.rows[last]), 32 * PLY_RUN):  # pieces of a few hundred MB at most
                xyz = self._xyz(row, min(32 * PLY_RUN, int(self.index.rows[last]) - row))
                inside = in_box(xyz, lower, upper)
                numbers.append(row + np.flatnonzero(inside))
                points.append(xyz[inside])
        return BoxRead(np.concatenate(numbers) if numbers else np.zeros(0, np.int64),
                       np.concatenate(points) if points else np.zeros((0, 3)))

    def close(self) -> None:
        """Let go of the file (and remove the scratch file)."""
        if self.cache is not None:
            self.cache.close()
            self.cache = None
        self.file.close()
