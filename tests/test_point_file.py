"""A tiled run's scans in a scratch file (``tiling.point_file``): the same points, read-only, the mesh and empty sets
left as they are; a full disk named; and the twin's writer, reading them part by part, leaves none of their pages
resident in the process."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from gdt_pipeline import Dataset, GdtError
from gdt_pipeline.tiling import point_file
from gdt_pipeline.tiling.point_file import spilled_points
from gdt_pipeline.types import MappedRows


def _scan(n: int, seed: int = 0) -> Dataset:
    return Dataset(name="scan", role="scan", points=np.random.default_rng(seed).normal(size=(n, 3)))


def _resident_kb(ds: Dataset) -> int:
    """The resident kB of this process's map of the dataset's scratch file (/proc/self/smaps, by address)."""
    start = ds.points.ctypes.data
    total, counting = 0, False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()
        if head and "-" in head[0] and len(head) >= 5:
            lo, hi = (int(x, 16) for x in head[0].split("-"))
            counting = lo <= start < hi
        elif counting and line.startswith("Rss:"):
            total += int(head[1])
    return total


def test_spilled_points_are_the_scans_read_only_and_meshes_stay(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                                                 ) -> None:
    monkeypatch.setattr(point_file, "WRITE_PIECE", 1000)  # several pieces, the last one short
    ds = _scan(4321)
    out = spilled_points(ds, tmp_path)
    assert isinstance(out.points, MappedRows) and not out.points.flags.writeable
    assert np.array_equal(np.asarray(out.points), ds.points)
    assert np.array_equal(out.points[np.array([4320, 0, 17])], ds.points[[4320, 0, 17]])
    assert list(tmp_path.iterdir()) == []  # an unnamed file: nothing is left beside the twin
    assert spilled_points(out, tmp_path) is out
    mesh = Dataset(name="cad", role="reference", points=np.eye(3), faces=np.array([[0, 1, 2]]))
    assert spilled_points(mesh, tmp_path) is mesh
    empty = _scan(0)
    assert spilled_points(empty, tmp_path) is empty


def test_a_full_disk_names_the_folder_and_the_room_needed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def full(fd: int, data: object, offset: int) -> int:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "pwrite", full)
    with pytest.raises(GdtError, match=rf"{tmp_path}: writing dataset 'scan' points.*No space left.*TMPDIR.*"
                                       r"0\.024 GB of points"):
        spilled_points(_scan(1_000_000), tmp_path)


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="needs /proc/self/smaps (Linux)")
def test_the_twins_writer_reads_spilled_points_in_parts_and_holds_none(tmp_path: Path) -> None:
    from gdt_pipeline.memory import return_freed_memory
    from gdt_pipeline.twin_elements import composite_to_elements
    from gdt_pipeline.types import Composite, CompositeItem

    ds = spilled_points(_scan(600_000, 1), tmp_path)  # 14 MB of points
    return_freed_memory()
    n = ds.n_elements
    item = CompositeItem(key="scan", dataset=ds, epoch="E0", state=np.zeros(n, np.uint8), score=np.zeros(n),
                         source_epoch=np.zeros(n, np.int32), visible=np.ones(n, bool))
    source = composite_to_elements(Composite(items=(item,)))[0]  # what the writer is handed: rows on demand
    parts = [source.rows(a, a + 100_000) for a in range(0, n, 100_000)]
    assert np.array_equal(np.concatenate([p.points for p in parts]), np.asarray(_scan(600_000, 1).points))
    assert _resident_kb(ds) < 1_000  # the parts hold copies; the map's pages went back to the page cache
