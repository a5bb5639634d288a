"""The tiles' core scores put in place as tiles finish (``tiling.score_sink``): every element's score, p-value,
coverage and winning candidate is its tile's, whatever order the tiles finish in; a tile without p-values gives
NaN, one without coverage is covered; the winning candidates are renumbered into the merged candidates' order;
and the pieces are let go as they are absorbed. Kept in scratch files (a tiled run's default), the columns are the same
and the process holds none of their pages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gdt_pipeline import GdtError, Scores
from gdt_pipeline.tiling.score_sink import ScoreSink
from gdt_pipeline.types import MappedRows

N, TILES = 1000, 6


@pytest.fixture(params=["memory", "disk"])
def folder(request: pytest.FixtureRequest, tmp_path: Path) -> Path | None:
    """Where the sink keeps its columns: in memory, or scratch files in a folder."""
    return tmp_path if request.param == "disk" else None


def _pieces(rng: np.random.Generator) -> tuple[list[np.ndarray], list[Scores], list[np.ndarray]]:
    """Core elements per tile, each tile's scores (tile 1 without p-values, tile 4 without coverage, tile 5's winners
    int64), and per tile
    where each of its candidates lands among the merged candidates."""
    tile_of = rng.integers(0, TILES, N)
    members = [np.flatnonzero(tile_of == t) for t in range(TILES)]
    pieces, maps, merged_at = [], [], 0
    for t, ids in enumerate(members):
        n = len(ids)
        candidates = 3 * n
        match = np.where(rng.uniform(size=n) < 0.8, rng.integers(0, candidates, n), -1)
        match = match.astype(np.int64 if t == 5 else np.int32)  # one tile's winners int64: the column widens
        pieces.append(Scores(query=0, score=rng.uniform(0, 9, n), measure="test",
                             p_value=None if t == 1 else rng.uniform(size=n), tolerance=0.01 * t,
                             match=match, covered=None if t == 4 else rng.uniform(size=n) < 0.5))
        maps.append(np.sort(rng.choice(10 * N, candidates, replace=False)).astype(np.int32) + merged_at)
        merged_at += 10 * N
    return members, pieces, maps


def test_scores_put_in_place_are_each_elements_tiles(folder: Path | None) -> None:
    members, pieces, maps = _pieces(np.random.default_rng(3))
    sink = ScoreSink([N], folder)
    for t in (4, 0, 5, 2, 1, 3):  # tiles finish in any order
        handed: list[Scores | None] = [pieces[t]]
        sink.absorb(t, handed, [members[t]])
        assert handed == [None]
    merged = sink.merged(0, list(range(TILES)), members, maps)
    for t, (ids, s) in enumerate(zip(members, pieces, strict=True)):
        assert np.array_equal(merged.score[ids], s.score)
        assert np.array_equal(merged.p_value[ids], np.full(len(ids), np.nan) if s.p_value is None else s.p_value,
                              equal_nan=True)
        assert np.array_equal(merged.covered[ids], np.ones(len(ids), bool) if s.covered is None else s.covered)
        won = s.match >= 0
        assert np.array_equal(merged.match[ids][won], maps[t][s.match[won]])
        assert (merged.match[ids][~won] == -1).all()
    assert merged.tolerance == pytest.approx(0.05) and merged.measure == "test"
    assert merged.match.dtype == np.int32
    # held as made, read-only: the scores do not copy them
    assert not merged.score.flags.writeable
    if folder is None:
        assert merged.score.base is None
    else:  # maps of unnamed scratch files: nothing left in the folder
        assert all(isinstance(c, MappedRows) for c in (merged.score, merged.p_value, merged.covered, merged.match))
        assert list(folder.iterdir()) == []


def test_without_merged_candidates_the_winners_keep_their_numbers(folder: Path | None) -> None:
    members, pieces, _ = _pieces(np.random.default_rng(4))
    sink = ScoreSink([N], folder)
    for t in range(TILES):
        sink.absorb(t, [pieces[t]], [members[t]])
    merged = sink.merged(0, list(range(TILES)), members, None)
    for ids, s in zip(members, pieces, strict=True):
        assert np.array_equal(merged.match[ids], s.match)
    assert merged.match.dtype == np.int64


def test_a_tile_missing_from_the_merge_is_an_error() -> None:
    members, pieces, maps = _pieces(np.random.default_rng(5))
    sink = ScoreSink([N])
    for t in range(TILES - 1):
        sink.absorb(t, [pieces[t]], [members[t]])
    with pytest.raises(GdtError, match="scores of tiles"):
        sink.merged(0, list(range(TILES)), members, maps)


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="needs /proc/self/smaps (Linux)")
def test_columns_on_disk_leave_no_pages_in_the_process(tmp_path: Path) -> None:
    """Each tile's writes go to the page cache as it is absorbed: after 8 MB of scores, none of the columns' pages
    are the process's (smaps, by the maps' addresses)."""
    n, tiles = 1_000_000, 4
    rng = np.random.default_rng(8)
    members = np.array_split(rng.permutation(n).astype(np.int32), tiles)
    sink = ScoreSink([n], tmp_path)
    given = [rng.uniform(size=len(ids)) for ids in members]
    for t, ids in enumerate(members):
        sink.absorb(t, [Scores(query=0, score=given[t], measure="test", p_value=given[t] / 2)], [ids])
    merged = sink.merged(0, list(range(tiles)), members, None)
    assert _resident_kb([merged.score, merged.p_value]) < 1_000
    assert np.array_equal(merged.score[members[2]], given[2])
    assert np.array_equal(merged.p_value[members[3]], given[3] / 2)
    assert _resident_kb([merged.score, merged.p_value]) < 1_000  # reads take pieces and let them go


def _resident_kb(columns: list[np.ndarray]) -> int:
    """The resident kB of this process's maps that hold the columns (/proc/self/smaps, by address)."""
    starts = [c.ctypes.data for c in columns]
    total, counting = 0, False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()
        if head and "-" in head[0] and len(head) >= 5:
            lo, hi = (int(x, 16) for x in head[0].split("-"))
            counting = any(lo <= s < hi for s in starts)
        elif counting and line.startswith("Rss:"):
            total += int(head[1])
    return total
