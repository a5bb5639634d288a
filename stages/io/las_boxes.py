"""LAS/LAZ and COPC read one box at a time (``ReaderSpec.boxes``): the same elements, numbered and valued as
:func:`~stages.io.las.read_las` gives them, while holding only the chunks that can hold the box's points.

- LAS/LAZ: a first pass over the file (a chunk at a time) records which cells of a coarse grid each run of records
  touches (``chunk_index``); a box then seeks to the runs that touch its cells. LAZ runs are the file's own LASzip
  chunks, so a seek starts at a chunk and decompresses nothing it does not return.
- COPC: the file's octree is the index. Nodes are the chunks; their cubes say where their points are (the COPC
  specification keeps every point inside its node's cube), so no first pass is needed unless a class filter or the
  colour scale asks for one.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from gdt_pipeline import BoxRead, InputError, ReadRequest

from . import las as las_io
from .cell_cache import CellCache, field_types
from .chunk_index import CellGrid, ChunkIndex, Indexed, in_box, runs

# Records per run of an uncompressed LAS (seeking there is free) and of a LAZ whose chunks vary in size.
LAS_RUN = 65_536
# Records decompressed at a time by a box read (about 8 MB of records in the common formats): what a box holds
# besides its own points.
BOX_PIECE = 262_144
_VARIABLE = 0xFFFFFFFF


def _laz_chunk_size(path: Path) -> int | None:
    """The LASzip chunk size of a compressed file (None when chunks vary in size, or the file is not compressed)."""
    with open(path, "rb") as fh:
        head = fh.read(375)
        header_size, offset, n_vlrs = (struct.unpack_from("<H", head, 94)[0], struct.unpack_from("<I", head, 96)[0],
                                       struct.unpack_from("<I", head, 100)[0])
        fh.seek(header_size)
        vlr = las_io.laszip_vlr(fh.read(offset - header_size), n_vlrs)
    if vlr is None:
        return None
    size = int(struct.unpack_from("<I", vlr, 12)[0])
    return None if size in (_VARIABLE, 0) else size


def _kept_xyz(records: Any, kept: np.ndarray) -> np.ndarray:
    """(N,3) scaled coordinates of the kept records."""
    return np.column_stack([np.asarray(records.x)[kept], np.asarray(records.y)[kept], np.asarray(records.z)[kept]])


def _is_copc(header: Any) -> bool:
    return bool(header.vlrs) and type(header.vlrs[0]).__name__ == "CopcInfoVlr"


class _ChunkedBoxes(Indexed):
    """What LAS and COPC box reads share: the index, the filter, and turning a run of records into a box's part."""

    index: ChunkIndex
    colour_top: int
    cache: CellCache | None = None

    def __init__(self, path: Path, classes: list[int] | None, attributes: tuple[str, ...]) -> None:
        self.path, self.classes, self.attributes = path, classes, attributes

    def _records(self, first: int, last: int) -> Iterator[Any]:
        """The point records of chunks [first, last), in file order, a bounded piece at a time."""
        raise NotImplementedError

    def _header(self) -> Any:
        raise NotImplementedError

    def _no_fields(self) -> dict[str, np.ndarray]:
        """The fields a box of no points has: those of the file's point format, empty."""
        from laspy import ScaleAwarePointRecord

        return las_io.attribute_rows(ScaleAwarePointRecord.zeros(0, header=self._header()), np.zeros(0, np.int64),
                                     self.attributes)

    def _kept(self, records: Any) -> np.ndarray:
        """Indices of the records the class filter keeps."""
        if self.classes is None:
            return np.arange(len(records))
        return np.flatnonzero(np.isin(np.asarray(records.classification), self.classes))

    def read_box(self, lower: np.ndarray, upper: np.ndarray) -> BoxRead:
        """The elements inside the closed box [lower, upper], numbered as the whole read numbers them."""
        lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
        if self.cache is not None:
            elements, xyz, raw = self.cache.read(lower, upper)
            return BoxRead(elements, xyz, las_io.scaled_colour(raw, self.colour_top))
        numbers: list[np.ndarray] = []
        points: list[np.ndarray] = []
        fields: dict[str, list[np.ndarray]] = {}
        try:
            for first, last in runs(self.index.chunks(lower, upper)):
                element = int(self.index.elements[first])
                for records in self._records(first, last):
                    kept = self._kept(records)
                    xyz = _kept_xyz(records, kept)
                    inside = in_box(xyz, lower, upper)
                    numbers.append(element + np.flatnonzero(inside))
                    points.append(xyz[inside])
                    for name, values in las_io.attribute_rows(records, kept[inside], self.attributes).items():
                        fields.setdefault(name, []).append(values)
                    element += len(kept)
                if element != self.index.elements[last]:
                    start, indexed = self.index.elements[first], self.index.elements[last]
                    raise InputError(f"{self.path}: chunks {first}-{last - 1} hold {element - start} points now, "
                                     f"{indexed - start} when the file was indexed (was it changed while being read?)")
        except InputError:
            raise
        except BaseException as exc:  # lazrs panics are BaseExceptions: see las.failure
            raise las_io.failure(self.path, "a box of the LAS/LAZ", exc) from exc
        merged = {name: np.concatenate(fields.get(name, [empty])) for name, empty in self._no_fields().items()}
        return BoxRead(np.concatenate(numbers) if numbers else np.zeros(0, np.int64),
                       np.concatenate(points) if points else np.zeros((0, 3)),
                       las_io.scaled_colour(merged, self.colour_top))

    def _scan(self, pieces: Iterator[tuple[np.ndarray, Any]], grid: CellGrid, n_chunks: int, per_chunk_cells: bool
              ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
        """One pass over (chunk of each record, records): per chunk the cells its kept points touch (when
        ``per_chunk_cells``), how many it keeps; and the kept points' extent. Also the file's largest colour."""
        n_cells = int(np.prod(grid.shape))
        keys: list[np.ndarray] = []
        kept_counts = np.zeros(n_chunks, np.int64)
        lower, upper = np.full(3, np.inf), np.full(3, -np.inf)
        self.colour_top = 0
        self.cell_totals = np.zeros(n_cells, np.int64)
        for chunk_of, records in pieces:
            kept = self._kept(records)
            xyz = _kept_xyz(records, kept)
            kept_counts += np.bincount(chunk_of[kept], minlength=n_chunks)
            if len(xyz):
                lower, upper = np.minimum(lower, xyz.min(axis=0)), np.maximum(upper, xyz.max(axis=0))
            if per_chunk_cells:
                point_cells = grid.flat(grid.index3(xyz))
                keys.append(np.unique(chunk_of[kept] * n_cells + point_cells))
                self.cell_totals += np.bincount(point_cells, minlength=n_cells)
            wanted = ("color",) if "color" in self.attributes else ()
            colour = las_io.attribute_rows(records, kept, wanted).get("color")
            if colour is not None:
                self.colour_top = max(self.colour_top, int(np.max(colour, initial=0)))
        cells: list[np.ndarray] = []
        if per_chunk_cells:
            pairs = np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)
            chunk_ids = pairs // n_cells
            cells = np.split(pairs % n_cells, np.searchsorted(chunk_ids, np.arange(1, n_chunks)))
        if not np.all(np.isfinite(lower)):
            lower = upper = np.zeros(3)
        return cells, kept_counts, lower, upper


class LasBoxes(_ChunkedBoxes):
    """A LAS/LAZ file indexed by a first pass: runs of records and the grid cells they touch; with ``sort_cells``, a
    second pass sorts its points by cell into a scratch file under ``scratch`` (the system's temporary folder by
    default), which box reads then read instead."""

    def __init__(self, path: Path, classes: list[int] | None, attributes: tuple[str, ...], sort_cells: bool = False,
                 scratch: Path | None = None) -> None:
        import laspy

        super().__init__(path, classes, attributes)
        self.total = las_io.check_las_header(path)
        self.reader = laspy.open(str(path))
        header = self.reader.header
        compressed = bool(getattr(header, "are_points_compressed", False))
        chunk = _laz_chunk_size(path) if compressed else LAS_RUN
        # seeking a LAZ lands on a chunk: the runs are its chunks; one whose chunks vary is read from the start
        self.seekable = chunk is not None
        self.run = chunk or LAS_RUN
        n_chunks = max(1, -(-self.total // self.run))
        grid = CellGrid.over(np.asarray(header.mins), np.asarray(header.maxs))
        rows = np.full(n_chunks, self.run, np.int64)
        rows[-1] = self.total - self.run * (n_chunks - 1)
        try:
            cells, kept, lower, upper = self._scan(self._all_pieces(), grid, n_chunks, True)
        except BaseException as exc:  # lazrs panics are BaseExceptions: see las.failure
            self.close()
            if isinstance(exc, InputError):
                raise
            raise las_io.failure(path, "LAS/LAZ while indexing it", exc) from exc
        self.index = ChunkIndex.of(grid, cells, rows, kept, lower, upper)
        if sort_cells:
            self.cache = self._sorted(grid, scratch)

    def _sorted(self, grid: CellGrid, scratch: Path | None) -> CellCache:
        """The second pass: every kept point, its number and fields into its cell's rows of a scratch file."""
        try:
            cache = CellCache(grid, self.cell_totals, field_types(self._no_fields()), scratch)
        except InputError as exc:
            self.close()
            raise InputError(f"{self.path}: {exc}") from exc
        try:
            element = 0
            for _, records in self._all_pieces():
                kept = self._kept(records)
                xyz = _kept_xyz(records, kept)
                cache.write(element + np.arange(len(kept)), xyz, las_io.attribute_rows(records, kept, self.attributes))
                element += len(kept)
            cache.check_full()
        except BaseException as exc:
            cache.close()
            self.close()
            if isinstance(exc, InputError):
                if str(self.path) in str(exc):
                    raise
                raise InputError(f"{self.path}: {exc}") from exc
            raise las_io.failure(self.path, "LAS/LAZ while sorting it by cell", exc) from exc
        return cache

    def _all_pieces(self) -> Iterator[tuple[np.ndarray, Any]]:
        read = 0
        for records in self._sequential(0, None):
            n = len(records)
            if read + n > self.total:
                raise InputError(f"{self.path}: the LAS header declares {self.total} points, but the file holds more")
            yield np.arange(read, read + n) // self.run, records
            read += n
        if read != self.total:
            raise InputError(f"{self.path}: the LAS header declares {self.total} points, laspy read {read}")

    def _sequential(self, start: int, stop: int | None) -> Iterator[Any]:
        """Records of rows [start, stop) (to the end for None), a bounded piece at a time."""
        if self.seekable:
            self.reader.seek(start)
        else:  # no seek into variable-size LAZ chunks: decompress from the start and drop what lies before
            import laspy

            self.reader.close()
            self.reader = laspy.open(str(self.path))
            skip = start
            while skip > 0:
                skip -= len(self.reader.read_points(min(skip, las_io.CHUNK_POINTS)))
        row = start
        while stop is None or row < stop:
            records = self.reader.read_points(las_io.CHUNK_POINTS if stop is None else min(BOX_PIECE, stop - row))
            if len(records) == 0:
                return
            row += len(records)
            yield records

    def _records(self, first: int, last: int) -> Iterator[Any]:
        yield from self._sequential(int(self.index.rows[first]), int(self.index.rows[last]))

    def _header(self) -> Any:
        return self.reader.header

    def close(self) -> None:
        """Let go of the file (and remove the scratch file)."""
        if self.cache is not None:
            self.cache.close()
            self.cache = None
        self.reader.close()


class CopcBoxes(_ChunkedBoxes):
    """A COPC file, its octree nodes the chunks: a box decompresses the nodes whose cubes it overlaps."""

    def __init__(self, path: Path, classes: list[int] | None, attributes: tuple[str, ...]) -> None:
        import laspy
        from laspy.copc import load_octree_for_query

        super().__init__(path, classes, attributes)
        total = las_io.check_las_header(path)
        try:
            self.reader = laspy.CopcReader.open(str(path))
            nodes = sorted(load_octree_for_query(self.reader.source, self.reader.copc_info, self.reader.root_page),
                           key=lambda node: node.offset)
        except BaseException as exc:  # lazrs panics are BaseExceptions: see las.failure
            raise las_io.failure(path, "the COPC hierarchy", exc) from exc
        self.offsets = np.array([n.offset for n in nodes], np.int64)
        self.sizes = np.array([n.byte_size for n in nodes], np.int64)
        counts = np.array([n.point_count for n in nodes], np.int64)
        if counts.sum() != total:
            self.close()
            raise InputError(f"{path}: the COPC hierarchy's nodes hold {int(counts.sum())} points, the LAS header "
                             f"declares {total}")
        header = self.reader.header
        grid = CellGrid.over(np.asarray(header.mins), np.asarray(header.maxs))
        self.counts = counts
        cells = [grid.cells_in(np.maximum(n.bounds.mins, header.mins), np.minimum(n.bounds.maxs, header.maxs))
                 for n in nodes]
        kept, lower, upper = counts, np.asarray(header.mins, np.float64), np.asarray(header.maxs, np.float64)
        self.colour_top = 0
        if classes is not None or "color" in attributes:  # what the filter keeps, and the file's colour scale
            rows = np.concatenate([[0], np.cumsum(counts)])
            pieces = ((np.searchsorted(rows, row + np.arange(len(r)), side="right") - 1, r)
                      for row, r in self._with_rows(0, len(nodes)))
            _, kept, lower, upper = self._scan(pieces, grid, len(nodes), False)
        self.index = ChunkIndex.of(grid, cells, counts, kept, lower, upper)

    def _with_rows(self, first: int, last: int) -> Iterator[tuple[int, Any]]:
        row = int(self.counts[:first].sum())
        for records in self._records(first, last):
            yield row, records
            row += len(records)

    def _records(self, first: int, last: int) -> Iterator[Any]:
        """Nodes [first, last) decompressed a group at a time (laspy keeps its per-node decompression private, so
        the nodes are read here as its ``CopcReader.query`` does: their bytes and lazrs's chunk-table call)."""
        import lazrs
        from laspy import PackedPointRecord, ScaleAwarePointRecord

        header = self.reader.header
        node = first
        while node < last:
            end = node + 1
            while (end < last and self.offsets[end] == self.offsets[end - 1] + self.sizes[end - 1]
                   and self.counts[node:end + 1].sum() <= BOX_PIECE):
                end += 1
            self.reader.source.seek(int(self.offsets[node]))
            compressed = self.reader.source.read(int(self.offsets[end - 1] + self.sizes[end - 1] - self.offsets[node]))
            n = int(self.counts[node:end].sum())
            out = np.zeros(n * header.point_format.size, np.uint8)
            table = [(int(c), int(s)) for c, s in zip(self.counts[node:end], self.sizes[node:end], strict=True)]
            lazrs.decompress_points_with_chunk_table(compressed, self.reader.laszip_vlr.record_data, out, table,
                                                     self.reader.decompression_selection)
            packed = PackedPointRecord.from_buffer(out, header.point_format)
            yield ScaleAwarePointRecord(packed.array, packed.point_format, header.scales, header.offsets)
            node = end

    def _header(self) -> Any:
        return self.reader.header

    def close(self) -> None:
        """Let go of the file."""
        self.reader.source.close()


def open_las_boxes(path: Path, classes: list[int] | None, attributes: tuple[str, ...], sort_cells: bool = False
                   ) -> LasBoxes | CopcBoxes:
    """A LAS/LAZ or COPC file opened for box reads: a COPC file through its octree, any other through a first pass
    (and, with ``sort_cells``, a second that sorts its points by cell into a scratch file)."""
    if _is_copc(las_io.las_header(path)):
        return CopcBoxes(path, classes, attributes)
    return LasBoxes(path, classes, attributes, sort_cells)


def las_boxes(req: ReadRequest) -> LasBoxes | CopcBoxes:
    """The reader's ``boxes``: the request's file opened for box reads, with its params' filter and attributes; a
    LAS/LAZ sorted by cell, since scanners write scan order, in which a tile touches a third of a file's runs."""
    return open_las_boxes(req.path, req.params.classes, tuple(req.params.attributes), sort_cells=True)
