"""Shared fixtures: small generated scenes, the plugin registry, and a helper to run the CLI as a user would."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import tempfile
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gdt_pipeline.memory import peak_rss_mb as peak_rss_mb  # re-exported: the tests measure with it

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
GDT = Path(sys.executable).with_name("gdt")


@pytest.fixture(scope="session")
def registry():
    """The registry of the stages installed in this environment (entry points only)."""
    from gdt_pipeline.plugins import load_registry

    return load_registry(blocked=())


def run_gdt(*args: str, cwd: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run the installed `gdt` command and capture its output."""
    full_env = {**os.environ, "COLUMNS": "200", **(env or {})}
    return subprocess.run([str(GDT), *args], cwd=cwd, env=full_env, capture_output=True, text=True, timeout=300)


@dataclass
class Metered:
    """A command's exit code, wall time, peak RSS (its own, see tests/child_meter.py) and why it was killed."""

    returncode: int
    seconds: float
    peak_mb: float
    killed: str


def run_metered(cmd: list[str], *, cwd: Path | None = None, env: dict | None = None, stdout: Any = None,
                stderr: Any = None, kill_seconds: float = 600.0, kill_rss_mb: float = 8192.0) -> Metered:
    """Run ``cmd`` through tests/child_meter.py so that its peak RSS is its own, not the pytest process's."""
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "result.json"
        subprocess.run([sys.executable, str(Path(__file__).with_name("child_meter.py")), str(result),
                        str(kill_seconds), str(kill_rss_mb), *cmd], cwd=cwd, env=env, stdout=stdout, stderr=stderr,
                       stdin=subprocess.DEVNULL, check=True)
        data = json.loads(result.read_text())
    return Metered(data["returncode"], data["seconds"], data["peak_mb"], data["killed"])


def reset_peak_rss() -> None:
    """Reset this process's peak RSS (VmHWM) to its current RSS, so a later ``peak_rss_mb`` measures one step."""
    Path("/proc/self/clear_refs").write_text("5")


@contextlib.contextmanager
def holding_writer_lock(twin: Path) -> Iterator[subprocess.Popen]:
    """Another process holds the twin's writer lock while the block runs (it is killed after)."""
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import time
        from twin_store import writer_lock
        with writer_lock({str(twin)!r}):
            print("locked", flush=True)
            time.sleep(60)
    """)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        yield holder
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()


def write_points_ply(path: Path, points: np.ndarray) -> None:
    """Write an ASCII PLY point cloud (so tests can also write NaNs and empty clouds)."""
    lines = ["ply", "format ascii 1.0", f"element vertex {len(points)}", "property float x", "property float y",
             "property float z", "end_header"]
    lines += [" ".join(repr(float(v)) for v in p) for p in points]
    path.write_text("\n".join(lines) + "\n")


@dataclass
class CubeScene:
    """A CAD cube (E0) and a noisy scan (E1) of the cube plus a new small box standing beside it."""

    dir: Path
    cad: Path
    scan: Path
    changed: np.ndarray  # ground truth per scan point: on the new box
    sigma: float


def make_cube_scene(root: Path, *, sigma: float = 0.002, seed: int = 0, n_cube: int = 4000, n_new: int = 1000
                    ) -> CubeScene:
    """Write the cube scene into ``root`` and return its paths and ground truth."""
    import trimesh

    root.mkdir(parents=True, exist_ok=True)
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cube.apply_translation((0, 0, 0.5))
    cube.export(root / "cad.obj")
    new = trimesh.creation.box(extents=(0.3, 0.3, 0.3))
    new.apply_translation((1.0, 0.0, 0.15))
    rng = np.random.default_rng(seed)
    p_cube = trimesh.sample.sample_surface(cube, n_cube, seed=seed)[0]
    p_new = trimesh.sample.sample_surface(new, n_new, seed=seed + 1)[0]
    # the new box touches the cube's x=0.5 face only at distance 0.35 (its x range is 0.85..1.15)
    pts = np.vstack([p_cube, p_new]) + rng.normal(0, sigma, (n_cube + n_new, 3))
    changed = np.r_[np.zeros(n_cube, bool), np.ones(n_new, bool)]
    write_points_ply(root / "scan.ply", pts)
    return CubeScene(root, root / "cad.obj", root / "scan.ply", changed, sigma)


CUBE_WORKFLOW = """\
name: cube
twin: {twin}
seed: 7
epochs:
  - id: E0
    role: as-designed
    inputs: [{{path: {cad}}}]
  - id: E1
    role: as-is
    inputs: [{{path: {scan}, name: scan}}]
stages:
  - uses: constant
    role: as-designed
    with: {{model: isotropic, sigma: 0.001}}
  - uses: identity
    role: as-is
  - uses: constant
    role: as-is
    with: {{model: isotropic, sigma: {sigma}}}
  - uses: nearest
    role: as-is
  - uses: {distance}
    role: as-is
  - uses: fixed
    role: as-is
    with: {{tau: {tau}}}
  - uses: keep_unchanged
"""


def write_cube_workflow(scene: CubeScene, *, twin: str = "twin", distance: str = "bhattacharyya", tau: float = 10.0,
                        name: str = "workflow.yaml") -> Path:
    """A workflow over the cube scene, written beside it."""
    text = CUBE_WORKFLOW.format(twin=twin, cad=scene.cad.name, scan=scene.scan.name, sigma=scene.sigma,
                                distance=distance, tau=tau)
    path = scene.dir / name
    path.write_text(textwrap.dedent(text))
    return path


@pytest.fixture
def cube_scene(tmp_path: Path) -> CubeScene:
    """A fresh cube scene in a temporary folder."""
    return make_cube_scene(tmp_path / "scene")
