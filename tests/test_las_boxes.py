"""LAS/LAZ and COPC read a box at a time: exactly the elements (numbers, coordinates, fields) the whole read puts in
the box, for many random boxes, with and without a class filter; and only the chunks that can hold them read."""

from __future__ import annotations

import tempfile
from pathlib import Path

import laspy
import numpy as np
import pytest

import stages.io.las as las_io
import stages.io.las_boxes as boxes_io
from gdt_pipeline import InputError
from gdt_pipeline.simulation.copc_file import write_copc


def _scan_like(n: int, rng: np.random.Generator) -> np.ndarray:
    """Points on a floor, a wall and a pipe, in a scanner's order (by azimuth about a station), so that runs of
    records are local as in a real scan."""
    k = n // 3
    floor = np.column_stack([rng.uniform(0, 8, k), rng.uniform(0, 5, k), rng.normal(0, 0.002, k)])
    wall = np.column_stack([rng.uniform(0, 8, k), rng.normal(5, 0.002, k), rng.uniform(0, 3, k)])
    t, h = rng.uniform(0, 2 * np.pi, n - 2 * k), rng.uniform(0, 8, n - 2 * k)
    pipe = np.column_stack([h, 2.5 + 0.3 * np.cos(t), 1.5 + 0.3 * np.sin(t)])
    pts = np.concatenate([floor, wall, pipe])
    azimuth = np.arctan2(pts[:, 1] - 2.5, pts[:, 0] - 4.0)
    return np.round(pts[np.argsort(azimuth, kind="stable")] / 1e-4) * 1e-4


def _write_las(path: Path, pts: np.ndarray, classes: np.ndarray, rgb: np.ndarray) -> None:
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales, header.offsets = [1e-4] * 3, [0.0, 0.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts.T
    las.classification = classes
    las.intensity = (np.arange(len(pts)) % 60000).astype(np.uint16)
    las.red, las.green, las.blue = rgb.T
    las.write(str(path))


def _boxes(rng: np.random.Generator, lower: np.ndarray, upper: np.ndarray, n: int) -> list[tuple[np.ndarray, ...]]:
    """Random boxes of a tenth to half the extent, and two that miss it, one that holds it all."""
    span = upper - lower
    out = []
    for _ in range(n):
        size = span * rng.uniform(0.1, 0.5, 3)
        lo = lower + rng.uniform(-0.1, 1.0, 3) * span - size / 2
        out.append((lo, lo + size))
    return [*out, (upper + 1, upper + 2), (lower - 2, lower - 1), (lower - 1, upper + 1)]


def _check_against_whole(source: boxes_io._ChunkedBoxes, path: Path, classes: list[int] | None,
                         rng: np.random.Generator) -> float:
    """Every box read equals the whole read's elements in that box; the mean share of chunks a box read."""
    whole, fields = las_io.read_las(path, classes, ("intensity", "color", "classification"))
    assert source.count == len(whole)
    assert np.array_equal(source.lower, whole.min(axis=0)) and np.array_equal(source.upper, whole.max(axis=0))
    shares = []
    for lo, hi in _boxes(rng, whole.min(axis=0), whole.max(axis=0), 12):
        got = source.read_box(lo, hi)
        want = np.flatnonzero(np.all((whole >= lo) & (whole <= hi), axis=1))
        assert np.array_equal(got.elements, want)
        assert np.array_equal(got.points, whole[want])
        assert set(got.fields) == set(fields)
        for name, values in fields.items():
            assert np.array_equal(got.fields[name], values[want]), name
        shares.append(len(source.index.chunks(lo, hi)) / source.index.n_chunks)
    return float(np.mean(shares[:-3]))


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("classes", [None, [2, 6]])
@pytest.mark.parametrize("sort_cells", [False, True])
def test_a_las_box_holds_what_the_whole_read_puts_there(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                         suffix: str, classes: list[int] | None,
                                                         sort_cells: bool) -> None:
    rng = np.random.default_rng(11)
    pts = _scan_like(60_000 if suffix == ".las" else 400_000, rng)  # laspy writes LAZ in chunks of 50,000
    path = tmp_path / f"scan{suffix}"
    rgb = rng.integers(0, 256, (len(pts), 3)).astype(np.uint16)  # 8-bit colour in 16-bit fields: scaled per file
    _write_las(path, pts, rng.choice([1, 2, 6], len(pts)).astype(np.uint8), rgb)
    monkeypatch.setattr(boxes_io, "LAS_RUN", 4096)
    monkeypatch.setattr(las_io, "CHUNK_POINTS", 10_000)  # first-pass pieces across runs
    monkeypatch.setattr(boxes_io, "BOX_PIECE", 3000)  # a box's pieces shorter than a run
    (tmp_path / "scratch").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "scratch"))  # where the scratch file goes
    source = boxes_io.open_las_boxes(path, classes, ("intensity", "color", "classification"), sort_cells)
    try:
        assert isinstance(source, boxes_io.LasBoxes)
        assert source.index.n_chunks == (len(pts) + source.run - 1) // source.run
        assert (source.cache is not None) == sort_cells
        assert not list((tmp_path / "scratch").iterdir())  # the scratch file has no name: a kill leaves nothing
        share = _check_against_whole(source, path, classes, rng)
    finally:
        source.close()
    assert not list((tmp_path / "scratch").iterdir())  # the scratch file goes with the source
    assert share < 0.45  # boxes of 0.1-12 % of the volume read a fifth of the chunks of a scan-ordered file


@pytest.mark.parametrize("classes", [None, [2]])
def test_a_copc_box_holds_what_the_whole_read_puts_there(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                          classes: list[int] | None) -> None:
    monkeypatch.setattr(boxes_io, "BOX_PIECE", 5000)  # groups of one or two nodes
    rng = np.random.default_rng(12)
    pts = _scan_like(90_000, rng)
    path = write_copc(tmp_path / "scan.copc.laz", pts, scale=1e-4, node_points=3000,
                      classification=rng.choice([1, 2], len(pts)), intensity=rng.integers(0, 9000, len(pts)))
    with laspy.CopcReader.open(str(path)) as reader:  # a COPC that laspy's own reader queries
        assert reader.header.point_count == len(pts)
        everything = reader.query()
    stored = np.column_stack([np.asarray(everything.x), np.asarray(everything.y), np.asarray(everything.z)])
    assert np.array_equal(np.unique(np.round(stored / 1e-4), axis=0), np.unique(np.round(pts / 1e-4), axis=0))
    source = boxes_io.open_las_boxes(path, classes, ("intensity", "color", "classification"))
    try:
        assert isinstance(source, boxes_io.CopcBoxes) and source.index.n_chunks > 8
        share = _check_against_whole(source, path, classes, rng)
    finally:
        source.close()
    assert share < 0.45  # a sixth of the nodes


def test_the_reader_offers_box_reads_and_a_bad_file_names_itself(tmp_path: Path) -> None:
    rng = np.random.default_rng(13)
    pts = _scan_like(20_000, rng)
    path = tmp_path / "scan.laz"
    _write_las(path, pts, np.full(len(pts), 2, np.uint8), np.zeros((len(pts), 3), np.uint16))
    assert las_io.READER.boxes is not None
    cut = tmp_path / "cut.laz"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(InputError, match=r"cut\.laz"):
        boxes_io.open_las_boxes(cut, None, ())


@pytest.mark.parametrize("sort_cells", [False, True])
def test_a_binary_ply_box_holds_what_the_whole_read_puts_there(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                sort_cells: bool) -> None:
    import open3d as o3d

    import stages.io.ply_boxes as ply_boxes
    from stages.io.ply import read_ply

    rng = np.random.default_rng(14)
    pts = _scan_like(50_000, rng)
    path = tmp_path / "scan.ply"
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)), write_ascii=False)
    monkeypatch.setattr(ply_boxes, "PLY_RUN", 2048)
    source = ply_boxes.PlyBoxes(path, sort_cells)
    whole = read_ply(path).vertices
    try:
        assert source.count == len(whole) and source.index.n_chunks == 25
        shares = []
        for lo, hi in _boxes(rng, whole.min(axis=0), whole.max(axis=0), 12):
            got = source.read_box(lo, hi)
            want = np.flatnonzero(np.all((whole >= lo) & (whole <= hi), axis=1))
            assert np.array_equal(got.elements, want) and np.array_equal(got.points, whole[want])
            shares.append(len(source.index.chunks(lo, hi)) / source.index.n_chunks)
    finally:
        source.close()
    assert np.mean(shares[:-3]) < 0.45
    bad = whole.copy()
    bad[30_001] = np.nan
    o3d.io.write_point_cloud(str(tmp_path / "nan.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(bad)),
                             write_ascii=False)
    with pytest.raises(InputError, match=r"nan\.ply: vertex row 30001 "):
        ply_boxes.PlyBoxes(tmp_path / "nan.ply")
    o3d.io.write_point_cloud(str(tmp_path / "text.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[:9])),
                             write_ascii=True)
    with pytest.raises(InputError, match=r"text\.ply: box reads need a binary PLY"):
        ply_boxes.PlyBoxes(tmp_path / "text.ply")


def test_sorting_by_cell_on_a_full_disk_says_so_and_leaves_nothing(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    import stages.io.cell_cache as cell_cache

    rng = np.random.default_rng(15)
    pts = _scan_like(20_000, rng)
    path = tmp_path / "scan.las"
    _write_las(path, pts, np.full(len(pts), 2, np.uint8), np.zeros((len(pts), 3), np.uint16))
    (tmp_path / "scratch").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "scratch"))
    monkeypatch.setattr(cell_cache.shutil, "disk_usage", lambda _: shutil._ntuple_diskusage(10**9, 10**9, 1000))
    with pytest.raises(InputError, match=r"scan\.las: .*scratch: sorting .*needs 1 MB of scratch space, 0 MB are free"):
        boxes_io.open_las_boxes(path, None, ("intensity",), sort_cells=True)
    assert not list((tmp_path / "scratch").iterdir())


def test_a_run_killed_while_its_points_sit_sorted_on_disk_leaves_no_scratch_file(tmp_path: Path) -> None:
    import os
    import signal
    import subprocess
    import sys

    rng = np.random.default_rng(16)
    pts = _scan_like(30_000, rng)
    path = tmp_path / "scan.las"
    _write_las(path, pts, np.full(len(pts), 2, np.uint8), np.zeros((len(pts), 3), np.uint16))
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    code = ("import pathlib, time, stages.io.las_boxes as b\n"
            f"s = b.open_las_boxes(pathlib.Path({str(path)!r}), None, ('intensity',), sort_cells=True)\n"
            "assert s.cache is not None and len(s.read_box(s.lower, s.upper).elements) == 30000\n"
            "print('open', flush=True)\ntime.sleep(60)\n")
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                             env={**os.environ, "TMPDIR": str(scratch)}, cwd=Path(__file__).resolve().parents[1])
    try:
        assert child.stdout.readline().strip() == "open"  # sorted into its scratch file, which it still holds
        child.send_signal(signal.SIGKILL)
        child.wait(30)
    finally:
        child.kill()
    assert not list(scratch.iterdir())
