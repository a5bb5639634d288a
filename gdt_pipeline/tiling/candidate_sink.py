"""The tiles' candidates kept on disk as tiles finish, and merged into element order on disk (``docs/scale.md``).

A candidate's columns (the matched position, the query position, the distance and, with the pooled expectation,
the query's covariance: 128 B; and the narrow ones, its element, reference item, element and row: 12–16 B) are
read again only by the null simulation, which draws 10⁵ pairs, by the fusion when it has no region of view (the
winning candidates), and by whoever takes a subset. So the process running the tiles writes each tile's columns to
an unnamed scratch file as the tile finishes and keeps only what is not one row a candidate (the reference models
of the candidates that carry one, scalars). The merge gathers the columns into element order in a second scratch
file, piece by piece, and hands them on as read-only maps of it (``MappedRows``): the merged ``Correspondences`` are
the same, value for value, as the ones merged in memory, and the epoch's candidates never sit in the process whole.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import IO, Any, overload

import numpy as np

from ..errors import GdtError
from ..memory import return_freed_memory
from ..scratch import read_at, scratch_file, scratch_folder, write_at
from ..types import Correspondences, GaussianUncertainty, MappedRows
from ..types.arrays import index_dtype
from ..types.correspondences import field_parts, scatter_rows
from ..types.uncertainty import concat_uncertainty

# Per-candidate arrays written to disk; the query's per-candidate Gaussian covariances go too ("query_cov").
WIDE_FIELDS = ("position", "query_position", "distance")
# the narrow ones: indices, read back a tile at a time to place the candidates
NARROW_FIELDS = ("element", "ref_item", "ref_element", "ref_row")
SPILLED = (*NARROW_FIELDS, *WIDE_FIELDS)
# ``ref_row`` of a tile whose candidates carry no model of their own: none (−1), as ``field_parts`` joins them
NO_ROW = -1
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
        maps = candidate_places(_TileColumn(self, held, "element"))
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
        values.update(self._on_disk(held, maps, total))
        columns = field_parts([h.narrow for h in held], kind, values, [h.size for h in held])
        for h in held:  # each column's parts are then held by ``columns`` alone, and go as the column is merged
            h.narrow = SimpleNamespace()
        for name, parts in columns.items():
            values[name] = scatter_rows(parts, maps, total)
            return_freed_memory()  # this column's parts, before the next column is made
        del columns
        if not held:
            values.update(ref_item=np.zeros(0, np.int32), ref_element=np.zeros(0, np.int32),
                          position=np.zeros((0, 3)), distance=np.zeros(0), element=np.zeros(0, np.int32))
        return_freed_memory()
        return kind(**values), maps

    def _hold(self, corr: Correspondences) -> _Held:
        columns: dict[str, _Column] = {}
        narrow = {f.name: getattr(corr, f.name) for f in dataclasses.fields(corr)}
        for name in SPILLED:
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

    def _column(self, h: _Held, name: str) -> np.ndarray:
        """One tile's column, read back whole."""
        return self._read(h.columns[name], 0, h.size)

    def _on_disk(self, held: list[_Held], maps: list[np.ndarray], total: int) -> dict[str, Any]:
        """The merged candidates' spilled fields: read-only maps of a scratch file in element order (and the
        reference models the merged ``ref_row`` indexes)."""
        names = [name for name in (*SPILLED, QUERY_COV) if any(name in h.columns for h in held)]
        for name in names:
            if name != "ref_row" and any(name not in h.columns for h in held):
                raise GdtError(f"tiles disagree on whether candidates carry {name!r}")
        out: dict[str, Any] = {}
        if "ref_row" in names:
            models = [h.narrow.ref_uncertainty for h in held if h.narrow.ref_uncertainty is not None]
            out["ref_uncertainty"] = concat_uncertainty(models, [m.rows for m in models])
        if not names:
            return out
        merged_file = scratch_file(self.folder, "gdt-candidates-merged-")
        # per tile, the run of its candidates that lands in each piece of GATHER_ROWS merged rows (one search for
        # all columns)
        edges = np.minimum(np.arange(0, total + GATHER_ROWS, GATHER_ROWS), total)
        runs = [np.searchsorted(places, edges) for places in maps]
        try:
            offset = 0
            for name in names:
                dtype, row_shape = _merged_type([h.columns.get(name) for h in held])
                if name == "ref_row":  # rows into the joined models: as many as all tiles' models hold
                    dtype = np.dtype(np.result_type(dtype, index_dtype(out["ref_uncertainty"].rows)))
                self._gather(merged_file, offset, [_Source(h.columns.get(name), shift) for h, shift in
                                                   zip(held, _row_shifts(held, name), strict=True)],
                             dtype, row_shape, maps, runs, total)
                mapped = _mapped(merged_file, offset, dtype, (total, *row_shape))
                offset += int(dtype.itemsize * np.prod(row_shape, dtype=np.int64)) * total
                if name == QUERY_COV:
                    out["query_uncertainty"] = GaussianUncertainty.trusted(mapped, held[0].query_dof)
                else:
                    out[name] = mapped
        finally:
            merged_file.close()  # the maps keep the file (each holds its own descriptor)
        return out

    def _gather(self, into: IO[bytes], offset: int, sources: list[_Source], dtype: np.dtype,
                row_shape: tuple[int, ...], maps: list[np.ndarray], runs: list[np.ndarray], total: int) -> None:
        """One column of every tile written into ``into`` at ``offset`` in element order, a piece at a time: piece
        k takes, from every tile, the contiguous run ``runs[tile][k]:runs[tile][k + 1]`` of its candidates."""
        row_bytes = int(dtype.itemsize * np.prod(row_shape, dtype=np.int64))
        for k, start in enumerate(range(0, total, GATHER_ROWS)):
            stop = min(total, start + GATHER_ROWS)
            piece = np.empty((stop - start, *row_shape), dtype=dtype)
            for source, places, run in zip(sources, maps, runs, strict=True):
                lo, hi = run[k], run[k + 1]
                if hi > lo:
                    piece[places[lo:hi] - start] = source.rows(self, int(lo), int(hi))
            self._put(into, piece, offset + row_bytes * start)

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


@dataclass(frozen=True)
class _Source:
    """Where one tile's rows of a merged column come from: its column in the arrival file, its rows shifted by
    ``shift`` where they are ≥ 0 (a ``ref_row`` into the joined models); no column: rows of ``NO_ROW``."""

    column: _Column | None
    shift: int = 0

    def rows(self, sink: CandidateSink, start: int, stop: int) -> np.ndarray:
        if self.column is None:
            return np.full(stop - start, NO_ROW)
        values = sink._read(self.column, start, stop)
        return np.where(values >= 0, values + np.int64(self.shift), NO_ROW) if self.shift else values


def _row_shifts(held: list[_Held], name: str) -> list[int]:
    """Per tile, what its rows of column ``name`` are shifted by: for ``ref_row``, the rows of the earlier tiles'
    models (their models joined in tile order, as ``field_parts`` joins them)."""
    if name != "ref_row":
        return [0] * len(held)
    shifts, rows = [], 0
    for h in held:
        shifts.append(rows)
        if h.narrow.ref_uncertainty is not None:
            rows += h.narrow.ref_uncertainty.rows
    return shifts


def _merged_type(columns: list[_Column | None]) -> tuple[np.dtype, tuple[int, ...]]:
    """The dtype and row shape of a merged column: the tiles' types promoted (an int64 index in one tile keeps its
    values)."""
    present = [c for c in columns if c is not None]
    dtype = np.result_type(*[c.dtype for c in present])
    if any(c is None for c in columns):
        dtype = np.result_type(dtype, np.int32)
    return np.dtype(dtype), present[0].row_shape


class _TileColumn(Sequence[np.ndarray]):
    """One column of each tile, read back from the arrival file when asked for (a pass over the tiles holds one
    tile's)."""

    def __init__(self, sink: CandidateSink, held: list[_Held], name: str) -> None:
        self.sink, self.held, self.name = sink, held, name

    def __len__(self) -> int:
        return len(self.held)

    @overload
    def __getitem__(self, i: int) -> np.ndarray: ...

    @overload
    def __getitem__(self, i: slice) -> list[np.ndarray]: ...

    def __getitem__(self, i: int | slice) -> np.ndarray | list[np.ndarray]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        return self.sink._column(self.held[i], self.name)


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
