"""Property tests of the built-in readers: random bytes and random mutations of valid files (truncations, flipped
bytes, changed header counts, inserted tokens) either read into a Dataset with finite coordinates and valid faces,
or raise a GdtError, never another exception (nor a Rust panic from lazrs, which is a BaseException)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gdt_pipeline import GdtError
from gdt_pipeline.plugins import load_registry
from gdt_pipeline.runner import read_dataset

from .conftest import peak_rss_mb, reset_peak_rss

REGISTRY = load_registry()
SEEDS = ("points.ply", "points_ascii.ply", "mesh.ply", "mesh_ascii.ply", "mesh.obj", "mesh.stl", "mesh_ascii.stl",
         "mesh.off", "mesh.glb", "cloud.xyz", "cloud.xyzn", "cloud.pts", "cloud.pcd", "cloud_ascii.pcd",
         "cloud_z.pcd", "scan.las", "scan.laz")
MAGIC = (b"", b"ply\nformat binary_little_endian 1.0\n", b"ply\nformat ascii 1.0\n", b"LASF", b"solid ", b"glTF",
         b"OFF\n", b"# .PCD v0.7\n")
SETTINGS = settings(max_examples=60, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _write_clouds(d: Path) -> None:
    import open3d as o3d

    rng = np.random.default_rng(5)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.normal(size=(40, 3))))
    pcd.normals = o3d.utility.Vector3dVector(rng.normal(size=(40, 3)))
    for name, opts in (("points.ply", {}), ("points_ascii.ply", {"write_ascii": True}), ("cloud.xyz", {}),
                       ("cloud.xyzn", {}), ("cloud.pts", {}), ("cloud.pcd", {}),
                       ("cloud_ascii.pcd", {"write_ascii": True}), ("cloud_z.pcd", {"compressed": True})):
        assert o3d.io.write_point_cloud(str(d / name), pcd, **opts)


def _write_meshes(d: Path) -> None:
    import trimesh

    mesh = trimesh.creation.icosphere(1)
    (d / "mesh.ply").write_bytes(trimesh.exchange.ply.export_ply(mesh))
    (d / "mesh_ascii.ply").write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="ascii"))
    (d / "mesh_ascii.stl").write_bytes(trimesh.exchange.stl.export_stl_ascii(mesh).encode())
    for ext in ("obj", "stl", "off", "glb"):
        mesh.export(str(d / f"mesh.{ext}"))


def _write_las(d: Path) -> None:
    import laspy

    pts = np.random.default_rng(6).uniform(0, 10, (60, 3))
    for ext in ("las", "laz"):
        las = laspy.LasData(laspy.LasHeader(point_format=3, version="1.2"))
        las.header.scales = np.array([0.01, 0.01, 0.01])
        las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
        las.write(str(d / f"scan.{ext}"))


@pytest.fixture(scope="module")
def seeds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One small valid file per format."""
    d = tmp_path_factory.mktemp("reader_seeds")
    _write_clouds(d)
    _write_meshes(d)
    _write_las(d)
    return d


def check_read(path: Path, kind: str | None = None) -> None:
    """The property: a Dataset with finite coordinates and faces in range, or a GdtError (nothing else)."""
    try:
        ds = read_dataset(path, REGISTRY, name="x", kind=kind)
    except GdtError:
        return
    assert np.isfinite(ds.points).all() and len(ds.points) > 0
    if ds.faces is not None:
        assert len(ds.faces) > 0 and ds.faces.min() >= 0 and ds.faces.max() < len(ds.points)


@st.composite
def mutated(draw: st.DrawFn, data: bytes) -> bytes:
    """``data`` after a few random edits: truncation, flipped bytes, a changed number, inserted tokens or bytes."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["truncate", "flip", "number", "token", "bytes"]))
        at = draw(st.integers(0, max(len(out) - 1, 0)))
        if op == "truncate":
            out = out[:at]
        elif op == "flip" and out:
            out[at] = draw(st.integers(0, 255))
        elif op == "number":
            numbers = list(re.finditer(rb"\d+", bytes(out[:600])))
            if numbers:
                m = draw(st.sampled_from(numbers))
                value = str(draw(st.sampled_from([0, 1, 2, 3, 7, 255, 65536, 10**9, 2**32 - 1, 10**18]))).encode()
                out[m.start():m.end()] = value
        elif op == "token":
            tok = draw(st.sampled_from([b" inf", b" nan", b" np.float64(0.1)", b"\n", b" -1", b" 1e400", b" 3"]))
            out[at:at] = tok
        else:
            out[at:at] = draw(st.binary(min_size=1, max_size=16))
    return bytes(out)


@pytest.mark.parametrize("seed", SEEDS)
def test_mutated_files_read_or_raise_a_gdt_error(seeds: Path, tmp_path: Path, seed: str) -> None:
    data = (seeds / seed).read_bytes()
    target = tmp_path / f"case{Path(seed).suffix}"

    @SETTINGS
    @given(mutated(data))
    def run(blob: bytes) -> None:
        target.write_bytes(blob)
        check_read(target)

    run()


@pytest.mark.parametrize("ext", [".ply", ".obj", ".stl", ".off", ".glb", ".xyz", ".pts", ".pcd", ".las", ".laz"])
def test_random_bytes_read_or_raise_a_gdt_error(tmp_path: Path, ext: str) -> None:
    target = tmp_path / f"case{ext}"

    @SETTINGS
    @given(st.sampled_from(MAGIC), st.binary(min_size=1, max_size=1500), st.sampled_from([None, "points", "mesh"]))
    def run(magic: bytes, blob: bytes, kind: str | None) -> None:
        target.write_bytes(magic + blob)
        check_read(target, kind)

    run()


def test_one_long_token_among_many_is_refused_without_allocating(tmp_path: Path) -> None:
    """numpy sizes a bytes array by its longest token: 800,000 rows and one 5 MB number must not ask for terabytes."""
    path = tmp_path / "bomb.xyz"
    path.write_bytes(b"1 2 3\n" * 800_000 + b"1" * 5_000_000 + b" 2 3\n")
    reset_peak_rss()  # the pytest process's earlier peak would hide this read's own
    before = peak_rss_mb()
    with pytest.raises(GdtError, match=r"line 800001 .*a token of 5000000 characters"):
        read_dataset(path, REGISTRY, name="bomb")
    assert peak_rss_mb() - before < 900
