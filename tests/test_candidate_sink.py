"""The tiles' candidates kept on disk as tiles finish: merged on disk they equal the candidates merged in memory,
field for field; their wide columns are read-only maps that a record holds without copying; taking rows of such a
map leaves few of its pages in the process; and the scratch files have no name in the folder."""

from __future__ import annotations

import errno
import os
import tempfile
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from gdt_pipeline import BoxUncertainty, Correspondences, GaussianUncertainty, GdtError, MixtureUncertainty
from gdt_pipeline.runner.stage_call import element_ordered
from gdt_pipeline.tiling import CandidateSink, candidate_places, candidate_sink, merge_correspondences, take_candidates
from gdt_pipeline.types import MappedRows, frozen_array

N_ELEMENTS, N_CANDIDATES, N_TILES = 400, 1000, 5


def _query_model(kind: str, sigma: np.ndarray) -> object:
    if kind == "box":
        return BoxUncertainty(np.repeat(sigma[:, None], 3, axis=1))
    return GaussianUncertainty.isotropic(sigma, {"gaussian": None, "student": 3.0}.get(kind))


def _tiles(kind: str, seed: int = 23) -> tuple[Correspondences, list[Correspondences]]:
    """A dataset's candidates (element-ordered, with mixture rows) and their pieces in ``N_TILES`` random tiles."""
    rng = np.random.default_rng(seed)
    m = N_CANDIDATES
    sigma = rng.uniform(0.001, 0.01, m)
    mix = MixtureUncertainty(np.ones((m, 1)), np.zeros((m, 1, 3)), np.broadcast_to(np.eye(3), (m, 1, 3, 3)) *
                             rng.uniform(1, 2, (m, 1, 1, 1)))
    tile_of = rng.integers(0, N_TILES, N_ELEMENTS)
    whole = element_ordered(Correspondences(
        0, rng.integers(-1, 3, m), rng.integers(0, 500, m), rng.normal(size=(m, 3)), rng.uniform(size=m), "test",
        element=rng.integers(0, N_ELEMENTS, m), n_elements=N_ELEMENTS, query_position=rng.normal(size=(m, 3)),
        query_uncertainty=_query_model(kind, sigma), ref_uncertainty=mix,
        ref_row=np.where(rng.uniform(size=m) < 0.5, np.arange(m), -1)))
    same = [lambda e: e] * 3
    parts = [take_candidates(whole, tile_of[whole.element] == t, lambda e: e, same, N_ELEMENTS)
             for t in range(N_TILES)]
    if kind == "mixed":  # a tile of one candidate: its one-row model is kept in memory until the merge spills it
        parts[2] = parts[2].take(np.array([0]))
    if kind == "empty":  # a tile without candidates (a crop of no points of this scan, as at 50 M points)
        parts[2] = parts[2].take(np.zeros(0, dtype=np.int64))
    return whole, parts


@pytest.mark.parametrize("kind", ["gaussian", "student", "box", "mixed", "empty"])
def test_candidates_merged_on_disk_equal_those_merged_in_memory(kind: str, tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(candidate_sink, "GATHER_ROWS", 97)  # gathered in eleven pieces, the last one short
    _, parts = _tiles(kind)
    in_memory, in_memory_where = merge_correspondences(list(parts), N_ELEMENTS, 0)
    order = [3, 0, 4, 1, 2]  # tiles finish in any order
    with CandidateSink(folder=tmp_path) as sink:
        for t in order:
            handed: list[Correspondences | None] = [parts[t]]
            sink.absorb(t, handed)
            assert handed == [None]  # the sink took the tile's candidates
        assert os.listdir(tmp_path) == []  # the scratch file has no name
        merged, where = sink.merged(0, list(range(N_TILES)), N_ELEMENTS)
    for a, b in zip(where, in_memory_where, strict=True):
        assert np.array_equal(a, b)
    for name in ("element", "ref_item", "ref_element", "ref_row", "position", "distance", "query_position"):
        assert np.array_equal(getattr(merged, name), getattr(in_memory, name)), name
    for name in ("element", "ref_item", "ref_element", "ref_row", "position", "distance", "query_position"):
        assert isinstance(getattr(merged, name), MappedRows), name
    u, v = merged.query_uncertainty, in_memory.query_uncertainty
    m = len(in_memory.ref_item)
    assert type(u) is type(v)
    assert np.array_equal(u.covariance(m), v.covariance(m))
    assert getattr(u, "dof", None) == getattr(v, "dof", None)
    if kind != "box":  # no tile's covariances read back into memory
        assert isinstance(u.cov, MappedRows)
    used = merged.ref_row >= 0
    assert np.array_equal(merged.ref_uncertainty.covs[merged.ref_row[used]],
                          in_memory.ref_uncertainty.covs[in_memory.ref_row[used]])
    picked = np.random.default_rng(1).integers(0, m, 300)  # what a null simulation takes
    assert np.array_equal(merged.take(picked).position, in_memory.take(picked).position)
    assert np.array_equal(u.take(picked).covariance(300), v.take(picked).covariance(300))
    assert os.listdir(tmp_path) == []


def test_a_tile_out_of_element_order_is_an_error(tmp_path: Path) -> None:
    _, parts = _tiles("gaussian")
    shuffled = parts[1].take(np.arange(len(parts[1].ref_item))[::-1])
    with CandidateSink(folder=tmp_path) as sink:
        for t, part in enumerate([parts[0], shuffled]):
            sink.absorb(t, [part])
        with pytest.raises(GdtError, match="tile 1: the candidates of dataset 0 are not in element order"):
            sink.merged(0, [0, 1], N_ELEMENTS)


@pytest.mark.parametrize("layout", ["disjoint tiles", "shared elements", "a piece out of order"])
def test_candidate_places_are_those_of_a_stable_sort(layout: str) -> None:
    rng = np.random.default_rng(8)
    tile_of = rng.integers(0, 6, 5000)
    pieces = [np.repeat(np.flatnonzero(tile_of == t), rng.integers(1, 4, int(np.sum(tile_of == t))))
              for t in range(6)] + [np.zeros(0, np.int64)]
    if layout == "shared elements":  # a piece with elements of other pieces: the places come from the sort
        pieces.append(np.sort(rng.integers(0, 5000, 700)))
    if layout == "a piece out of order":
        pieces[2] = pieces[2][::-1].copy()
    joined = np.concatenate(pieces)
    stable = np.empty(len(joined), np.int64)
    stable[np.argsort(joined, kind="stable")] = np.arange(len(joined))
    places = candidate_places(pieces)
    assert all(p.dtype == np.int32 for p in places)
    assert np.array_equal(np.concatenate(places), stable)


def test_the_sink_holds_no_column_of_its_candidates(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Traced by numpy's allocations: the tiles' candidates wait on disk, narrow columns too (they were 12 B a
    candidate in memory), and the merge holds where each candidate goes (4 B a candidate) and one tile's column
    at a time; the merged candidates are maps of the merged file."""
    monkeypatch.setattr(candidate_sink, "GATHER_ROWS", 1024)
    rng = np.random.default_rng(4)
    n, tiles = 100_000, 8
    tile_of = rng.integers(0, tiles, n)
    tracemalloc.start()
    try:
        with CandidateSink(folder=tmp_path) as sink:
            before, _ = tracemalloc.get_traced_memory()
            for t in range(tiles):
                e = np.repeat(np.flatnonzero(tile_of == t), 2)
                sink.absorb(t, [Correspondences(0, np.zeros(len(e)), np.arange(len(e)), np.zeros((len(e), 3)),
                                                np.zeros(len(e)), "test", element=e, n_elements=n)])
            del e
            m = 2 * n
            held, _ = tracemalloc.get_traced_memory()
            tracemalloc.reset_peak()
            merged, where = sink.merged(0, list(range(tiles)), n)
            _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert held - before < 4096 * tiles  # the tiles' records, none of their columns (12 B a candidate: 2.4 MB)
    # where each candidate goes, the elements' counts and first places, and one tile's column and its runs
    assert peak - held <= 4 * m + 8 * n + 24 * m / tiles
    assert merged.element.dtype == merged.ref_item.dtype == merged.ref_element.dtype == np.int32
    for name in ("element", "ref_item", "ref_element"):
        assert isinstance(getattr(merged, name), MappedRows), name
    assert np.array_equal(merged.element, np.repeat(np.arange(n), 2))
    assert sum(len(w) for w in where) == m


def test_a_full_scratch_disk_names_the_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _, parts = _tiles("gaussian")

    def full(fd: int, data: object, offset: int) -> int:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "pwrite", full)
    with CandidateSink(folder=tmp_path) as sink, pytest.raises(GdtError, match=f"{tmp_path}.*set TMPDIR"):
        sink.absorb(0, [parts[0]])


def _mapped(rows: int, folder: Path) -> tuple[MappedRows, np.ndarray]:
    values = np.random.default_rng(3).normal(size=(rows, 3))
    with tempfile.TemporaryFile(dir=folder) as f:
        f.write(values.tobytes())
        f.flush()
        return MappedRows(f, dtype=np.float64, mode="r", shape=values.shape), values


def _resident_kb(arr: np.ndarray) -> int:
    """The resident size of the mapping that holds ``arr`` (``/proc/self/smaps``)."""
    address = arr.ctypes.data
    inside = False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()[0]
        if "-" in head and all(c in "0123456789abcdef-" for c in head):
            lo, hi = (int(x, 16) for x in head.split("-"))
            inside = lo <= address < hi
        elif inside and line.startswith("Rss:"):
            return int(line.split()[1])
    raise AssertionError("mapping not found")


def test_mapped_rows_are_held_as_they_are_and_read_only(tmp_path: Path) -> None:
    mapped, values = _mapped(1000, tmp_path)
    held = frozen_array(mapped, np.float64, (None, 3), "rows")
    assert held is mapped
    assert not held.flags.writeable
    with pytest.raises(ValueError):
        held[0, 0] = 1.0
    pick = np.random.default_rng(0).integers(0, 1000, 257)
    assert np.array_equal(mapped[pick], values[pick])
    mask = np.zeros(1000, bool)
    mask[pick] = True
    assert np.array_equal(mapped[mask], values[mask])
    assert np.array_equal(mapped[10:20], values[10:20])
    copied = frozen_array(values[::2], np.float64, (None, 3), "rows")
    assert not np.shares_memory(copied, values)


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="needs /proc/self/smaps (Linux)")
def test_taking_random_rows_leaves_few_pages_mapped(tmp_path: Path) -> None:
    mapped, values = _mapped(4_000_000, tmp_path)  # 96 MB
    pick = np.random.default_rng(0).integers(0, len(values), 100_000)
    taken = mapped[pick]
    assert np.array_equal(taken, values[pick])
    # a plain map would hold every page the 100,000 rows touched: nearly all of its 96 MB
    assert _resident_kb(mapped) < 8 * 1024
