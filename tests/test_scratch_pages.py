"""Scratch files' pages: passes over rows kept on disk (the scans' covariances at 72 B a point) give what the same
rows in memory give, and leave none of the file's pages resident in the process (``/proc/self/smaps``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gdt_pipeline import GaussianUncertainty
from gdt_pipeline.types import MappedRows


def _resident_kb(path_part: str) -> int:
    """The resident kB of this process's maps of files whose name holds ``path_part`` (/proc/self/smaps)."""
    total, counting = 0, False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()
        if head and "-" in head[0] and len(head) >= 5:
            counting = len(head) >= 6 and path_part in line
        elif counting and line.startswith("Rss:"):
            total += int(head[1])
    return total


def _scratch_rows(folder: Path, values: np.ndarray) -> MappedRows:
    """``values`` written to a scratch file and mapped back read-only (a name in ``folder``, so smaps shows it)."""
    path = folder / "rows.bin"
    values.tofile(path)
    return MappedRows(path, dtype=values.dtype, mode="r", shape=values.shape)


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="needs /proc/self/smaps (Linux)")
def test_scratch_maps_let_go_of_their_pages_when_memory_is_returned(tmp_path: Path) -> None:
    """A pass over a scratch file's rows leaves its pages resident; ``return_freed_memory`` lets go of them, and the
    rows still read the same."""
    from gdt_pipeline.memory import return_freed_memory

    values = np.random.default_rng(1).normal(size=(200_000, 3, 3))
    rows = _scratch_rows(tmp_path, values)
    assert float(np.asarray(rows).view(np.ndarray).sum()) == pytest.approx(float(values.sum()))
    assert _resident_kb("rows.bin") > 10_000  # 14 MB read
    return_freed_memory()
    assert _resident_kb("rows.bin") == 0
    assert np.array_equal(rows[np.array([0, 199_999])], values[[0, 199_999]])


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="needs /proc/self/smaps (Linux)")
def test_packed_covariances_of_a_scratch_map_equal_the_in_memory_ones_and_leave_no_pages(tmp_path: Path) -> None:
    """What the twin stores of covariances kept on disk (packed rows, the RMS summary) is what it stores of the same
    rows in memory, and the passes, a piece at a time, leave no page of the file resident."""
    from gdt_pipeline.types import arrays

    rng = np.random.default_rng(2)
    a = rng.normal(size=(arrays.PASS_PIECE * 2 + 17, 3, 3))
    values = a @ np.swapaxes(a, 1, 2)
    rows = _scratch_rows(tmp_path, values)
    on_disk = GaussianUncertainty.trusted(rows, None)
    in_memory = GaussianUncertainty(values)
    assert on_disk.covariance(len(values)) is rows
    assert np.array_equal(on_disk.stored(len(values))["covariance"], in_memory.stored(len(values))["covariance"])
    assert np.array_equal(on_disk.summary(len(values)), in_memory.summary(len(values)))
    assert _resident_kb("rows.bin") == 0


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="needs /proc/self/smaps (Linux)")
def test_search_reach_of_covariances_on_disk_equals_in_memory_and_leaves_no_pages(tmp_path: Path) -> None:
    """The correspondence search's reach per element (the tile halos' input, a pass over every covariance of the
    epoch) is the same over rows kept in a scratch file, and leaves none of the file's pages resident: the whole
    file stayed resident before (3.7 GB at 50 M points, between the region of view and the first tile)."""
    from gdt_pipeline.types import arrays
    from stages.correspondence.directed_search import element_variances

    rng = np.random.default_rng(3)
    a = rng.normal(size=(arrays.PASS_PIECE + 5, 3, 3))
    values = a @ np.swapaxes(a, 1, 2)
    on_disk = GaussianUncertainty.trusted(_scratch_rows(tmp_path, values), None)
    expected = np.einsum("nii->n", values)
    assert np.array_equal(element_variances(on_disk, len(values)), expected)
    assert _resident_kb("rows.bin") == 0
    shared = GaussianUncertainty(values[:1])
    assert np.array_equal(element_variances(shared, 4), np.full(4, expected[0]))


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="needs /proc/self/smaps (Linux)")
def test_depth_image_votes_over_covariances_on_disk_equal_in_memory_and_leave_no_pages(tmp_path: Path) -> None:
    """A station's votes read its points' covariances at random; over rows kept in a scratch file they are the same
    votes, and the pages they touched are let go of after each chunk of samples."""
    from gdt_pipeline.memory import track_scratch_map
    from gdt_pipeline.region_of_view.depth import Station, build_image, window_votes

    rng = np.random.default_rng(4)
    n = 300_000
    pts = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), np.full(n, 3.0) + rng.normal(0, 1e-3, n)])
    values = np.broadcast_to(np.diag([1e-6, 1e-6, 1e-6]), (n, 3, 3)).copy()
    rows = _scratch_rows(tmp_path, values)
    track_scratch_map(rows._mmap)
    station = Station(np.zeros(3), lambda q: np.ones(len(q), dtype=bool), (0,))
    samples = np.column_stack([rng.uniform(-0.9, 0.9, (50_000, 2)), np.full(50_000, 3.0)])
    sample_cov = np.broadcast_to(np.eye(3) * 1e-6, (len(samples), 3, 3))
    in_memory = window_votes(build_image(station, pts, values, 1.0), samples, sample_cov, None, 3.0)
    on_disk = window_votes(build_image(station, pts, rows, 1.0), samples, sample_cov, None, 3.0)
    assert in_memory[0].sum() > len(samples)  # the samples lie on the measured plane: present votes
    assert np.array_equal(on_disk, in_memory)
    assert _resident_kb("rows.bin") == 0
