"""LAS/LAZ read a chunk at a time: the same points, in the same order, as laspy reading the whole file, across
chunk boundaries and with a class filter."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest

import stages.io.las as las_io


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_chunks_read_what_the_whole_file_holds(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, suffix: str) -> None:
    rng = np.random.default_rng(3)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = [0.001, 0.001, 0.001]
    header.offsets = [500000.0, 4000000.0, 100.0]
    las = laspy.LasData(header)
    n = 5003
    las.x = 500000 + rng.uniform(0, 50, n)
    las.y = 4000000 + rng.uniform(0, 50, n)
    las.z = 100 + rng.uniform(0, 5, n)
    las.classification = rng.choice([1, 2, 6], n).astype(np.uint8)
    path = tmp_path / f"cloud{suffix}"
    las.write(str(path))
    whole = laspy.read(str(path))
    expected = np.column_stack([np.asarray(whole.x), np.asarray(whole.y), np.asarray(whole.z)])
    monkeypatch.setattr(las_io, "CHUNK_POINTS", 777)  # seven chunks, the last one short
    assert np.array_equal(las_io.read_las_points(path, None), expected)
    ground = np.isin(np.asarray(whole.classification), [2, 6])
    assert np.array_equal(las_io.read_las_points(path, [2, 6]), expected[ground])
