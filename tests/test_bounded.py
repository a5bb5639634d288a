"""Small bad inputs stay small: an alias bomb, a units mistake, a radius or spacing far off the data's scale end in
exit 1 with the cause named, in bounded time and memory (measured on the child process with ``os.wait4``)."""

from __future__ import annotations

import os
import subprocess
import tempfile
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gdt_pipeline.errors import StageError
from gdt_pipeline.geometry.extent import check_radius
from gdt_pipeline.workflow.marks import parse_bounded

from .conftest import GDT, make_cube_scene, run_metered, write_cube_workflow

BOMB = "l0: &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
    f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]\n" for i in range(1, 10))


@dataclass(frozen=True)
class Measured:
    """A finished `gdt` process: exit code, output, wall time and peak resident memory."""

    code: int
    out: str
    seconds: float
    peak_mb: float


def _gdt(*args: str, cwd: Path | None = None) -> Measured:
    """Run `gdt` and measure its wall time and its own peak RSS (tests/child_meter.py)."""
    env = {**os.environ, "COLUMNS": "200"}
    with tempfile.TemporaryFile() as fh:
        m = run_metered([str(GDT), *args], cwd=cwd, env=env, stdout=fh, stderr=subprocess.STDOUT)
        fh.seek(0)
        out = fh.read().decode(errors="replace")
    return Measured(m.returncode, out, m.seconds, m.peak_mb)


def test_alias_bomb_is_refused_in_the_loader_at_once() -> None:
    tracemalloc.start()
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=r"^bomb.yaml:\d+:\d+: .*too many nodes after alias expansion"):
        parse_bounded(BOMB, "bomb.yaml")
    seconds = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(BOMB) < 1024
    assert seconds < 1.0 and peak < 20 * 2**20, (seconds, peak)


def test_alias_bomb_costs_validate_nothing_beyond_its_start(tmp_path: Path) -> None:
    """`gdt validate` on a 1 KB alias bomb (6.9 GB and 44 s before the loader counted nodes) costs what validating a
    one-line file costs: starting the tool and loading its plugins (about 1 s and 200 MB here)."""
    tiny, bomb = tmp_path / "tiny.yaml", tmp_path / "bomb.yaml"
    tiny.write_text("name: tiny\n")
    bomb.write_text("name: bomb\n" + BOMB)
    base = _gdt("validate", str(tiny))
    res = _gdt("validate", str(bomb))
    assert base.code == 1 and res.code == 1, res.out
    assert "too many nodes after alias expansion" in res.out and f"{bomb}:" in res.out
    assert res.seconds < base.seconds + 1.0, (res.seconds, base.seconds)
    assert res.peak_mb < base.peak_mb + 100, (res.peak_mb, base.peak_mb)


def test_oversized_workflow_file_is_refused_before_parsing(tmp_path: Path) -> None:
    big = tmp_path / "big.yaml"
    big.write_text("name: big\ndescription: '" + "x" * (5 * 2**20) + "'\n")
    res = _gdt("validate", str(big))
    assert res.code == 1 and "bytes; more than" in res.out and "is not a workflow file" in res.out, res.out


@pytest.mark.parametrize(("old", "new", "says"), [
    ("name: scan}", "name: scan, units: mm}", "the scan is 1/789 of the size"),  # a metre scan read as mm
    ("path: cad.obj}", "path: cad.obj, units: mm}", "the scan is 1,267× the size")])  # a metre CAD read as mm
def test_units_mistake_is_named_early_with_bounded_memory(tmp_path: Path, old: str, new: str, says: str) -> None:
    """`units: mm` on a metre scan, or on the metre CAD: exit 1 naming `units`, in bounded memory, no twin."""
    scene = make_cube_scene(tmp_path / "scene")
    wf = write_cube_workflow(scene)
    wf.write_text(wf.read_text().replace(old, new))
    res = _gdt("run", "-q", str(wf))
    assert res.code == 1, res.out
    assert "check `units`" in res.out and says in res.out, res.out
    assert res.peak_mb < 1024 and res.seconds < 60, (res.peak_mb, res.seconds)
    assert not (scene.dir / "twin").exists()


def test_segment_radius_spanning_the_data_is_refused(tmp_path: Path) -> None:
    """Every scan element changed and a segment radius 100× the scene: refused before the all-pairs list is built."""
    scene = make_cube_scene(tmp_path / "scene")
    wf = write_cube_workflow(scene, tau=1e-9)
    wf.write_text(wf.read_text().replace("  - uses: keep_unchanged\n",
                                         "  - uses: keep_unchanged\n    with: {segment_radius: 100}\n"))
    res = _gdt("run", "-q", str(wf))
    assert res.code == 1, res.out
    assert "radius 100" in res.out and "extent" in res.out and "check `units`" in res.out, res.out
    assert res.peak_mb < 1024 and res.seconds < 60, (res.peak_mb, res.seconds)


def test_registration_spacing_far_below_the_data_is_refused(tmp_path: Path) -> None:
    """ICP voxels of 10 µm on a metre CAD would sample about 10^11 points: refused, naming the spacing."""
    scene = make_cube_scene(tmp_path / "scene")
    wf = write_cube_workflow(scene)
    wf.write_text(wf.read_text().replace("  - uses: identity\n    role: as-is\n",
                                         "  - uses: gicp\n    role: as-is\n    with: {voxels: [0.00001]}\n"))
    res = _gdt("run", "-q", str(wf))
    assert res.code == 1, res.out
    assert "sampling the twin at spacing 5e-06" in res.out and "check `units`" in res.out, res.out
    assert res.peak_mb < 1024 and res.seconds < 60, (res.peak_mb, res.seconds)


def test_radius_check_passes_valid_searches_and_names_the_bad_one() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 1, (20000, 3))
    tree = cKDTree(pts)
    check_radius(tree, 0.02, "test", "a search")  # about 0.7 neighbours each: the normal case
    t0 = time.perf_counter()
    with pytest.raises(StageError, match=r"test: a search of radius 2 .* extent \(bounding-box diagonal\) is 1.7"):
        check_radius(tree, 2.0, "test", "a search")  # every pair: 2·10^8 of them, counted without a list
    assert time.perf_counter() - t0 < 5.0


def test_a_dense_noisy_scan_with_many_neighbours_at_its_own_scale_passes() -> None:
    """The paper test scene's ToF scan joins ~600 changed elements to each at its 12 cm segment radius, 1/23 of its
    extent: many neighbours, but at the data's scale and a few million pairs. That must pass; the same count with a
    radius spanning the data, or a pair list beyond memory, must not."""
    rng = np.random.default_rng(1)
    plane = np.column_stack([rng.uniform(0, 2, 60_000), rng.uniform(0, 2, 60_000), rng.normal(0, 0.01, 60_000)])
    tree = cKDTree(plane)
    pairs = (tree.count_neighbors(tree, 0.08) - len(plane)) / 2
    assert 2.0 * pairs / len(plane) > 200 and pairs > 1_000_000  # the case the limits must let through
    check_radius(tree, 0.08, "test", "a search")
    with pytest.raises(StageError, match=r"radius 0.5 would join"):
        check_radius(tree, 0.5, "test", "a search")  # a quarter of the extent: another scale
