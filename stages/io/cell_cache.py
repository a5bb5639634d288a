"""A file's points sorted by the cells of a coarse grid, on disk, so that a box reads what lies in its cells and
little else.

A scanner writes its points in scan order: a run of 50,000 records is a thin wedge from the station to the far wall,
and a tile of a tenth of a room touches a third of the runs (``docs/scale.md``). A second pass over the file writes
each point, its element number and its fields into the cell's slot of one scratch file (an external bucket sort:
the first pass counted the cells), then a box reads the rows of the cells it overlaps. The file is a scratch file
(``gdt_pipeline.scratch``): unnamed, written and read a piece at a time.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from gdt_pipeline import InputError
from gdt_pipeline.scratch import read_at, scratch_file, scratch_folder, write_at

from .chunk_index import CellGrid, in_box


class CellCache:
    """Rows sorted by cell in a scratch file in ``folder``: ``starts[c]`` the first row of cell c (with the total at
    the end)."""

    def __init__(self, grid: CellGrid, counts: np.ndarray, fields: dict[str, tuple[np.dtype, tuple[int, ...]]],
                 folder: Path | None = None) -> None:
        self.grid = grid
        self.row = np.dtype([("element", "<i8"), ("xyz", "<f8", (3,)),
                             *((name, dt, shape) for name, (dt, shape) in fields.items())])
        self.starts = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)])
        need = int(self.starts[-1]) * self.row.itemsize
        self.folder = scratch_folder(folder)
        free = shutil.disk_usage(self.folder).free
        if need > free:
            raise InputError(f"{self.folder}: sorting the points by cell needs {need / 2**20:,.0f} MB of scratch "
                             f"space, {free / 2**20:,.0f} MB are free (set TMPDIR to a larger disk)")
        self._file = scratch_file(self.folder, "gdt-cells-")
        self._file.truncate(need)
        self._need = need
        self._cursor = self.starts[:-1].copy()

    def write(self, elements: np.ndarray, xyz: np.ndarray, fields: dict[str, np.ndarray]) -> None:
        """Add a piece of the file (its rows in file order): each row into its cell's next free slot."""
        cells = self.grid.flat(self.grid.index3(xyz))
        order = np.argsort(cells, kind="stable")  # stable: rows of a cell stay in file (element) order
        rows = np.empty(len(order), self.row)
        rows["element"], rows["xyz"] = elements[order], xyz[order]
        for name, values in fields.items():
            rows[name] = values[order]
        sorted_cells = cells[order]
        firsts = np.flatnonzero(np.r_[True, sorted_cells[1:] != sorted_cells[:-1]])
        for a, b in zip(firsts, np.r_[firsts[1:], len(order)], strict=True):
            cell = int(sorted_cells[a])
            write_at(self._file, rows[a:b], int(self._cursor[cell]) * self.row.itemsize, self.folder,
                     "the points sorted by cell", f"{self._need / 2**20:,.0f} MB")
            self._cursor[cell] += b - a

    def check_full(self) -> None:
        """Every cell got the rows the first pass counted (else the file changed between the passes)."""
        if not np.array_equal(self._cursor, self.starts[1:]):
            short = int(np.flatnonzero(self._cursor != self.starts[1:])[0])
            raise InputError(f"cell {short} got {int(self._cursor[short] - self.starts[short])} points on the second "
                             f"pass, {int(self.starts[short + 1] - self.starts[short])} on the first (was the file "
                             f"changed while being read?)")

    def read(self, lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """The rows inside the closed box [lower, upper], in element order: elements, coordinates, fields."""
        cells = np.sort(self.grid.cells_in(lower, upper))
        parts = []
        breaks = np.flatnonzero(np.diff(cells) != 1) + 1
        for run in np.split(cells, breaks):
            start, stop = int(self.starts[run[0]]), int(self.starts[run[-1] + 1])
            if stop > start:
                rows = read_at(self._file, self.row, (stop - start,), start * self.row.itemsize)
                parts.append(rows[in_box(rows["xyz"], lower, upper)])
        rows = np.concatenate(parts) if parts else np.zeros(0, self.row)
        rows = rows[np.argsort(rows["element"], kind="stable")]
        names = [n for n in self.row.names if n not in ("element", "xyz")]
        return rows["element"].copy(), rows["xyz"].copy(), {n: rows[n].copy() for n in names}

    def close(self) -> None:
        """Let go of the scratch file (it has no name to remove)."""
        self._file.close()


def field_types(sample: dict[str, np.ndarray]) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    """Each field's dtype and per-row shape, from a (possibly empty) sample of them."""
    return {name: (values.dtype, values.shape[1:]) for name, values in sample.items()}


def cell_counts(grid: CellGrid, pieces: Iterable[np.ndarray]) -> np.ndarray:
    """How many of the pieces' points fall in each cell of ``grid``."""
    total = np.zeros(int(np.prod(grid.shape)), np.int64)
    for xyz in pieces:
        total += np.bincount(grid.flat(grid.index3(xyz)), minlength=len(total))
    return total
