"""The tiles' core scores written into place as each tile finishes (``docs/scale.md``).

Kept as pieces until the last tile, every tile's scores (the score, the p-value, the coverage and the winning
candidate: 21 B a point) sat beside one another, and the merge then joined each column and put it in element order
(two more copies of it): at 50 M points a gigabyte held through the tile run and more at its merge. Here each
tile's columns go into the merged columns as it finishes, and the tile's piece goes. A tile without p-values gives
NaN, one without coverage is covered, and the winning candidates are renumbered into the merged candidates' order,
as joining the pieces did.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import GdtError
from ..types import Scores


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


def _room(n: int, dtype: type | np.dtype) -> np.ndarray:
    """An unfilled column: its pages are the process's only once a tile writes them (every element is in one
    tile's core), so the columns grow with the tiles absorbed instead of being held whole from the first."""
    return np.empty(n, dtype=dtype)


def _put(into: _Columns, name: str, ids: np.ndarray, values: np.ndarray | None, missing: float | bool | int,
         n: int) -> np.ndarray | None:
    """Column ``name`` with a tile's ``values`` at ``ids`` (``missing`` where the tile has none); made when a
    first tile has values, the tiles before it given ``missing``; widened when a tile's values need a wider type."""
    column: np.ndarray | None = getattr(into, name)
    if column is None and values is None:
        return None
    if column is None or (values is not None and np.result_type(column, values) != column.dtype):
        wider = _room(n, values.dtype if column is None else np.result_type(column, values))  # type: ignore[union-attr]
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
    columns: dict[int, _Columns] = field(default_factory=dict)

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
                into = self.columns[d] = _Columns(_room(self.sizes[d], np.float64), s.measure, s.query)
            into.score[ids] = s.score
            into.p_value = _put(into, "p_value", ids, s.p_value, np.nan, self.sizes[d])
            into.covered = _put(into, "covered", ids, s.covered, True, self.sizes[d])
            into.match = _put(into, "match", ids, s.match, -1, self.sizes[d])
            if s.tolerance is not None:
                into.tolerances.append(s.tolerance)
            into.tiles.append(tile)
            into.members.append(ids)
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
            dtype = np.result_type(*[m.dtype for m in candidate_maps]) if len(candidate_maps) else match.dtype
            out = np.full(len(match), -1, dtype=dtype)
            for ids, places in zip(members, candidate_maps, strict=True):
                local = match[ids]
                won = local >= 0
                out[ids[won]] = places[local[won]]
            match = out
        for column in (got.score, got.p_value, got.covered, match):
            if column is not None:  # frozen here, the scores hold them without a copy
                column.setflags(write=False)
        return Scores(query=got.query, score=got.score, measure=got.measure, p_value=got.p_value,
                      tolerance=max(got.tolerances) if got.tolerances else None, match=match, covered=got.covered)
