"""The tiles' core scores written into place as each tile finishes (``docs/scale.md``).

Kept as pieces until the last tile, every tile's scores (the score, the p-value, the coverage and the winning
candidate: 21 B a point) sat beside one another, and the merge then joined each column and put it in element order
(two more copies of it): at 50 M points a gigabyte held through the tile run and more at its merge. Here each
tile's columns go into the merged columns as it finishes, and the tile's piece goes. A tile without p-values gives
NaN, one without coverage is covered, and the winning candidates are renumbered into the merged candidates' order,
as joining the pieces did.

With a ``folder`` (a tiled run that keeps its bulk on disk, the default) the columns are scratch files there,
reserved in full and mapped: the pages a tile writes go to the page cache as it is absorbed, and the merged scores
hold read-only ``MappedRows`` of them, so that the process holds none of the 21 B a point through the rest of the run.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import GdtError
from ..memory import release_pages, track_scratch_map
from ..scratch import reserved_map
from ..types import MappedRows, Scores


@dataclass
class _Columns:
    """One dataset's merged columns so far, and what the tiles said of themselves."""

    score: np.ndarray
    measure: str
    query: int
    p_value: np.ndarray | None = None
    covered: np.ndarray | None = None
    match: np.ndarray | None = None
    tolerances: list[float] = field(default_factory=list)
    tiles: list[int] = field(default_factory=list)  # in the order absorbed
    members: list[np.ndarray] = field(default_factory=list)  # their core elements, in that order


@dataclass(frozen=True)
class _Room:
    """Where the columns live: in memory, or in scratch files in ``folder``."""

    folder: Path | None

    def column(self, n: int, dtype: type | np.dtype) -> np.ndarray:
        """An unfilled column. In memory its pages are the process's only once a tile writes them (every element
        is in one tile's core), so the columns grow with the tiles absorbed; in a scratch file, they are not."""
        if self.folder is None or n == 0:
            return np.empty(n, dtype=dtype)
        file, rows = reserved_map(self.folder, "gdt-scores-", dtype, (n,), "the tiles' scores")
        file.close()  # the map holds the file open, and frees it when it goes
        return rows

    @staticmethod
    def let_go(columns: Sequence[np.ndarray | None]) -> None:
        """Hand the pages a tile wrote to scratch-file columns to the page cache (memory columns keep theirs)."""
        for column in columns:
            pages = getattr(column, "_mmap", None)
            if pages is not None:
                release_pages(pages)

    @staticmethod
    def read_only(column: np.ndarray) -> np.ndarray:
        """The column frozen: itself, or a ``MappedRows`` of its scratch file, whose reads take pieces."""
        if isinstance(column, np.memmap) and column._mmap is not None:
            column.flush()
            column = column.view(MappedRows)  # shares the map (np.memmap's view keeps it), not made by MappedRows
            track_scratch_map(column._mmap)
        column.setflags(write=False)
        return column


def _put(into: _Columns, name: str, ids: np.ndarray, values: np.ndarray | None, missing: float | bool | int,
         n: int, room: _Room) -> np.ndarray | None:
    """Column ``name`` with a tile's ``values`` at ``ids`` (``missing`` where the tile has none); made when a
    first tile has values, the tiles before it given ``missing``; widened when a tile's values need a wider type."""
    column: np.ndarray | None = getattr(into, name)
    if column is None and values is None:
        return None
    if column is None or (values is not None and np.result_type(column, values) != column.dtype):
        wider = room.column(n, values.dtype if column is None else np.result_type(column, values))  # type: ignore[union-attr]
        for earlier in into.members:
            wider[earlier] = missing if column is None else column[earlier]
        column = wider
    column[ids] = missing if values is None else values
    return column


@dataclass
class ScoreSink:
    """Per recent dataset (``sizes``: its elements), the tiles' core scores in element order, filled as tiles
    finish; the winning candidates stay in each tile's numbering until ``merged`` renumbers them."""

    sizes: Sequence[int]
    folder: Path | None = None
    columns: dict[int, _Columns] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.room = _Room(self.folder)

    def absorb(self, tile: int, pieces: list[Scores | None], members: Sequence[np.ndarray]) -> None:
        """Put tile ``tile``'s scores of each dataset at its core elements ``members[d]``, and empty ``pieces``."""
        for d, s in enumerate(pieces):
            if s is None:
                continue
            ids = members[d]
            if len(s.score) != len(ids):
                raise GdtError(f"tile {tile}: {len(s.score)} scores of dataset {d} for {len(ids)} core elements")
            into = self.columns.get(d)
            if into is None:
                into = self.columns[d] = _Columns(self.room.column(self.sizes[d], np.float64), s.measure, s.query)
            into.score[ids] = s.score
            into.p_value = _put(into, "p_value", ids, s.p_value, np.nan, self.sizes[d], self.room)
            into.covered = _put(into, "covered", ids, s.covered, True, self.sizes[d], self.room)
            into.match = _put(into, "match", ids, s.match, -1, self.sizes[d], self.room)
            if s.tolerance is not None:
                into.tolerances.append(s.tolerance)
            into.tiles.append(tile)
            into.members.append(ids)
            self.room.let_go([into.score, into.p_value, into.covered, into.match])
            pieces[d] = None

    def merged(self, d: int, tiles: Sequence[int], members: Sequence[np.ndarray],
               candidate_maps: Sequence[np.ndarray] | None) -> Scores:
        """Dataset ``d``'s scores of ``tiles`` (``members[i]``: tile i's core elements), the winning candidates
        renumbered through ``candidate_maps`` (per tile, tile candidate → merged candidate) when given."""
        got = self.columns.pop(d)
        if sorted(got.tiles) != sorted(tiles):
            raise GdtError(f"dataset {d}: scores of tiles {sorted(got.tiles)} absorbed, {sorted(tiles)} merged")
        match = got.match
        if match is not None and candidate_maps is not None:
            match = self._renumbered(match, members, candidate_maps)
        columns = [None if c is None else self.room.read_only(c) for c in (got.score, got.p_value, got.covered, match)]
        score, p_value, covered, match = columns  # frozen here, the scores hold them without a copy
        return Scores(query=got.query, score=score, measure=got.measure, p_value=p_value,
                      tolerance=max(got.tolerances) if got.tolerances else None, match=match, covered=covered)

    def _renumbered(self, match: np.ndarray, members: Sequence[np.ndarray], candidate_maps: Sequence[np.ndarray]
                    ) -> np.ndarray:
        """The winning candidates in the merged candidates' numbering (in the maps' type: in place when the column
        has it), tile by tile."""
        dtype = np.result_type(*[m.dtype for m in candidate_maps]) if len(candidate_maps) else match.dtype
        out = match if match.dtype == dtype else self.room.column(len(match), dtype)
        for ids, places in zip(members, candidate_maps, strict=True):
            local = match[ids]  # a copy: rewriting it in place is safe
            won = local >= 0
            out[ids[~won]] = -1
            out[ids[won]] = places[local[won]]
            self.room.let_go([out, match])
        return out
