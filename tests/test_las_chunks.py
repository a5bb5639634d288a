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


def test_intensity_and_colour_come_along_chunk_by_chunk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(4)
    n = 3001
    for bits, path in ((16, tmp_path / "rgb16.laz"), (8, tmp_path / "rgb8.las")):
        las = laspy.LasData(laspy.LasHeader(point_format=3, version="1.2"))
        las.x, las.y, las.z = rng.uniform(0, 10, (3, n))
        las.intensity = rng.integers(0, 65535, n).astype(np.uint16)
        top = (1 << bits) - 1
        rgb = rng.integers(0, top + 1, (n, 3)).astype(np.uint16)
        rgb[0] = top  # the scale is told by the largest value a channel holds
        las.red, las.green, las.blue = rgb.T
        las.classification = rng.choice([1, 2], n).astype(np.uint8)
        las.write(str(path))
        monkeypatch.setattr(las_io, "CHUNK_POINTS", 1000)
        ground = np.asarray(laspy.read(str(path)).classification) == 2
        pts, fields = las_io.read_las(path, [2])
        assert len(pts) == int(ground.sum()) == len(fields["intensity"]) == len(fields["color"])
        assert np.array_equal(fields["intensity"], np.asarray(las.intensity, np.float32)[ground])
        assert np.allclose(fields["color"], rgb[ground] / top, atol=1e-7)
        assert las_io.read_las(path, None, ())[1] == {}
    plain = laspy.LasData(laspy.LasHeader(point_format=1, version="1.2"))  # no RGB in format 1
    plain.x, plain.y, plain.z = rng.uniform(0, 10, (3, 10))
    plain.write(str(tmp_path / "plain.las"))
    assert set(las_io.read_las(tmp_path / "plain.las", None)[1]) == {"intensity"}
