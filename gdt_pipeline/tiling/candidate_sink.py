"""The tiles' candidates kept on disk as tiles finish, and merged into element order on disk (``docs/scale.md``).

A candidate's wide columns (the matched position, the query position, the distance and, with the pooled
expectation, the query's covariance: 128 B of the 160 B a candidate holds) are read again only by the null
simulation, which draws 10⁵ pairs, and by whoever takes a subset. So the process running the tiles writes each
tile's wide columns to an unnamed scratch file as the tile finishes and keeps only the narrow ones (items, elements,
rows: 24–32 B a candidate). The merge gathers the wide columns into element order in a second scratch file, piece by
piece, and hands them on as read-only maps of it (``MappedRows``): the merged ``Correspondences`` are the same,
value for value, as the ones merged in memory, and the epoch's candidates never sit in the process whole.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import IO, Any

import numpy as np

from ..errors import GdtError
from ..memory import return_freed_memory
from ..scratch import read_at, scratch_file, scratch_folder, write_at
from ..types import Correspondences, GaussianUncertainty, MappedRows
from ..types.arrays import index_dtype
from ..types.correspondences import field_parts, scatter_rows

# Per-candidate arrays written to disk; the query's per-candidate Gaussian covariances go too ("query_cov").
WIDE_FIELDS = ("position", "query_position", "distance")
QUERY_COV = "query_cov"
# Merged candidates gathered and written at a time: 2¹⁸ rows of the widest column (a covariance) are 19 MB.
GATHER_ROWS = 1 << 18


@dataclass(frozen=True)
class _Column:
    """One wide column of one tile's candidates in the arrival file."""

    offset: int
    dtype: np.dtype
    row_shape: tuple[int, ...]

    @property
    def row_bytes(self) -> int:
        return int(self.dtype.itemsize * np.prod(self.row_shape, dtype=np.int64))


@dataclass
class _Held:
    """One tile's candidates of one dataset: the narrow fields in memory, the wide ones in the arrival file."""

    kind: type
    narrow: SimpleNamespace
    columns: dict[str, _Column]
    size: int
    query_dof: float | None = None


@dataclass
class CandidateSink:
    """Per recent dataset, the finished tiles' candidates, their wide columns on disk in ``folder`` (TMPDIR)."""

    folder: Path = field(default_factory=scratch_folder)
    held: dict[int, dict[int, _Held]] = field(default_factory=dict)
    _file: IO[bytes] | None = None
    _end: int = 0

    def __enter__(self) -> CandidateSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Let go of the arrival file (the merged columns' file lives as long as their maps)."""
        if self._file is not None:
            self._file.close()
            self._file = None
        self.held.clear()

    def absorb(self, tile: int, pieces: list[Correspondences | None]) -> None:
        """Write tile ``tile``'s candidates' wide columns to disk, keep the rest, and empty ``pieces``."""
        for d, corr in enumerate(pieces):
            if corr is None:
                continue
            self.held.setdefault(d, {})[tile] = self._hold(corr)
            pieces[d] = None

    def merged(self, d: int, tiles: Sequence[int], n_elements: int) -> tuple[Correspondences, list[np.ndarray]]:
        """Dataset ``d``'s candidates of ``tiles`` in element order, and per tile where each of its candidates
        went (as ``merge_correspondences``)."""
        held = [self.held[d].pop(t) for t in tiles]
        maps = candidate_places([h.narrow.element for h in held])
        for t, places in zip(tiles, maps, strict=True):
            if np.any(places[1:] <= places[:-1]):  # the gather reads each tile's candidates in runs
                raise GdtError(f"tile {t}: the candidates of dataset {d} are not in element order")
        total = sum(h.size for h in held)
        kind = held[0].kind if held else Correspondences
        values: dict[str, Any] = {"query": d, "n_elements": n_elements,
                                  "method": held[0].narrow.method if held else ""}
        self._spill_small_models(held)
        if not _one_gaussian(held):
            self._query_models_back(held)
        columns = field_parts([h.narrow for h in held], kind, values)
        for h in held:  # each column's parts are then held by ``columns`` alone, and go as the column is merged
            h.narrow = SimpleNamespace()
        for name, parts in columns.items():
            values[name] = scatter_rows(parts, maps, total)
            return_freed_memory()  # this column's parts, before the next column is made
        del columns
        values.update(self._wide(held, maps, total))
        return_freed_memory()
        return kind(**values), maps

    def _hold(self, corr: Correspondences) -> _Held:
        columns: dict[str, _Column] = {}
        narrow = {f.name: getattr(corr, f.name) for f in dataclasses.fields(corr)}
        for name in WIDE_FIELDS:
            if narrow[name] is not None:
                columns[name] = self._write(np.ascontiguousarray(narrow[name]))
                narrow[name] = None
        u = corr.query_uncertainty
        dof = None
        if isinstance(u, GaussianUncertainty) and u.rows == len(corr.ref_item) and u.rows > 1:
            columns[QUERY_COV], dof = self._write(np.ascontiguousarray(u.cov)), u.dof
            narrow["query_uncertainty"] = None
        return _Held(type(corr), SimpleNamespace(**narrow), columns, len(corr.ref_item), dof)

    def _write(self, values: np.ndarray) -> _Column:
        if self._file is None:
            self._file = scratch_file(self.folder, "gdt-candidates-")
        column = _Column(self._end, values.dtype, values.shape[1:])
        self._put(self._file, values, self._end)
        self._end += values.nbytes
        return column

    def _put(self, file: IO[bytes], values: np.ndarray, offset: int) -> None:
        write_at(file, values, offset, self.folder, "the tiles' candidates", "about 130 B a candidate, twice")

    def _read(self, column: _Column, start: int, stop: int) -> np.ndarray:
        assert self._file is not None
        return read_at(self._file, column.dtype, (stop - start, *column.row_shape),
                       column.offset + column.row_bytes * start)

    def _wide(self, held: list[_Held], maps: list[np.ndarray], total: int) -> dict[str, Any]:
        """The wide fields of the merged candidates: read-only maps of a scratch file in element order."""
        names = sorted({name for h in held for name in h.columns})
        for name in names:
            if any(name not in h.columns for h in held):
                raise GdtError(f"tiles disagree on whether candidates carry {name!r}")
        if not names:
            return {}
        merged_file = scratch_file(self.folder, "gdt-candidates-merged-")
        out: dict[str, Any] = {}
        # per tile, the run of its candidates that lands in each piece of GATHER_ROWS merged rows (one search for
        # all columns)
        edges = np.minimum(np.arange(0, total + GATHER_ROWS, GATHER_ROWS), total)
        runs = [np.searchsorted(places, edges) for places in maps]
        try:
            offset = 0
            for name in names:
                first = held[0].columns[name]
                self._gather(merged_file, offset, [h.columns[name] for h in held], maps, runs, total)
                mapped = _mapped(merged_file, offset, first.dtype, (total, *first.row_shape))
                offset += first.row_bytes * total
                if name == QUERY_COV:
                    out["query_uncertainty"] = GaussianUncertainty.trusted(mapped, held[0].query_dof)
                else:
                    out[name] = mapped
        finally:
            merged_file.close()  # the maps keep the file (each holds its own descriptor)
        return out

    def _gather(self, into: IO[bytes], offset: int, columns: list[_Column], maps: list[np.ndarray],
                runs: list[np.ndarray], total: int) -> None:
        """One wide column of every tile written into ``into`` at ``offset`` in element order, a piece at a time:
        piece k takes, from every tile, the contiguous run ``runs[tile][k]:runs[tile][k + 1]`` of its candidates."""
        first = columns[0]
        for k, start in enumerate(range(0, total, GATHER_ROWS)):
            stop = min(total, start + GATHER_ROWS)
            piece = np.empty((stop - start, *first.row_shape), dtype=first.dtype)
            for column, places, run in zip(columns, maps, runs, strict=True):
                lo, hi = run[k], run[k + 1]
                if hi > lo:
                    piece[places[lo:hi] - start] = self._read(column, int(lo), int(hi))
            self._put(into, piece, offset + first.row_bytes * start)

    def _spill_small_models(self, held: list[_Held]) -> None:
        """The query models of tiles with at most one candidate (``_hold`` spills per-candidate rows only) written to
        disk too, where they are Gaussians of the spilled tiles' dof: else one such tile reads every tile's
        covariances back into memory (72 B a candidate, 6.3 GB at 50 M points)."""
        dofs = {h.query_dof for h in held if QUERY_COV in h.columns}
        if len(dofs) != 1:
            return
        dof = dofs.pop()
        for h in held:
            if QUERY_COV in h.columns:
                continue
            u = h.narrow.query_uncertainty
            if h.size == 0:  # no candidates: nothing of its model is merged, whatever it is
                cov = np.zeros((0, 3, 3))
            elif isinstance(u, GaussianUncertainty) and u.dof == dof and len(u.cov) in (1, h.size):
                cov = np.broadcast_to(u.cov, (h.size, 3, 3))
            else:
                continue
            h.columns[QUERY_COV], h.query_dof = self._write(np.ascontiguousarray(cov)), dof
            h.narrow.query_uncertainty = None

    def _query_models_back(self, held: list[_Held]) -> None:
        """The query's spilled covariances read back into memory, where tiles' models differ (some not Gaussian
        per candidate, or of another dof): they are merged in memory, as without the sink."""
        for h in held:
            if QUERY_COV in h.columns:
                cov = self._read(h.columns.pop(QUERY_COV), 0, h.size).copy()
                cov.setflags(write=False)
                h.narrow.query_uncertainty = GaussianUncertainty.trusted(cov, h.query_dof)


def _one_gaussian(held: list[_Held]) -> bool:
    """Whether every tile's query models went to disk as Gaussians of one dof (or none did)."""
    spilled = [QUERY_COV in h.columns for h in held]
    return not any(spilled) or (all(spilled) and len({h.query_dof for h in held}) == 1)


def candidate_places(elements: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Per piece, where each of its candidates goes when all are put in element order (stable, piece by piece);
    each piece's places increase, since its candidates are in element order already."""
    total = sum(len(e) for e in elements)
    places = _places_by_count(elements, index_dtype(total))
    return places if places is not None else _places_by_sorting(elements, index_dtype(total))


def _places_by_count(elements: Sequence[np.ndarray], dtype: type[np.signedinteger[Any]]) -> list[np.ndarray] | None:
    """``candidate_places`` from each element's candidate count, without sorting all candidates (a sort's three
    int64 arrays were 24 B a candidate at the merge's peak): an element's candidates start after those of the lower
    elements. It holds when each piece is in element order and no element has candidates in two pieces (tiles' cores
    are disjoint); None otherwise. A piece's runs are found again in each pass rather than kept (16 B an element)."""
    if not all(_in_order(e) for e in elements):
        return None
    n = max((int(e[-1]) + 1 for e in elements if len(e)), default=0)
    counts = np.zeros(n, dtype=dtype)
    for e in elements:
        first, length = _runs(e)
        counts[first] += length.astype(dtype)  # first holds each element once: no index repeats
    for e in elements:
        first, length = _runs(e)
        if np.any(counts[first] != length):  # the element has candidates in another piece too
            return None
    starts = np.cumsum(counts, dtype=dtype)
    starts -= counts
    del counts
    out = []
    for e in elements:
        first, length = _runs(e)
        run_start = np.cumsum(length, dtype=dtype) - length.astype(dtype)
        places = np.arange(len(e), dtype=dtype)
        places -= np.repeat(run_start, length)  # rank within the element's run
        places += np.repeat(starts[first], length)
        out.append(places)
    return out


def _in_order(element: np.ndarray) -> bool:
    """Whether a piece's candidates are in element order (and name elements, ≥ 0)."""
    return not len(element) or bool(element[0] >= 0 and np.all(element[1:] >= element[:-1]))


def _runs(element: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct elements of a piece in element order, and the length of each one's run of candidates."""
    if not len(element):
        return element, np.zeros(0, np.int64)
    bounds = np.r_[0, np.flatnonzero(element[1:] != element[:-1]) + 1, len(element)]
    return element[bounds[:-1]], np.diff(bounds)


def _places_by_sorting(elements: Sequence[np.ndarray], dtype: type[np.signedinteger[Any]]) -> list[np.ndarray]:
    """``candidate_places`` by a stable sort of all candidates: for pieces out of order, or sharing elements."""
    sizes = [len(e) for e in elements]
    joined = np.concatenate(elements) if elements else np.zeros(0, np.int64)
    order = np.argsort(joined, kind="stable")
    del joined
    where = np.empty(len(order), dtype=dtype)
    where[order] = np.arange(len(order), dtype=dtype)
    offsets = np.r_[0, np.cumsum(sizes)]
    return [where[offsets[i]:offsets[i + 1]] for i in range(len(sizes))]


def _mapped(file: IO[bytes], offset: int, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    """Rows of ``file`` at ``offset`` as a read-only map (an empty array when there are none: nothing to map)."""
    if shape[0] == 0:
        empty = np.zeros(shape, dtype=dtype)
        empty.setflags(write=False)
        return empty
    return MappedRows(file, dtype=dtype, mode="r", offset=offset, shape=shape)
