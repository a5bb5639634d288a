"""Issue 35: appends are safe. A SIGKILL at every named step of an append leaves the previous twin (or, once
swapped, the grown one) openable, verified and complete, and the next append completes; a second writer is refused
with the holder's pid; a workflow that changes a held epoch, or ``--from`` an unknown epoch, is exit 1 naming it and
leaves the twin untouched; ``gdt add`` appends a scan with the recorded chain, as a workflow epoch would."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from gdt_pipeline.runner import run_workflow
from twin_store import FAULT_STEPS, TwinStore

from .conftest import (
    GDT,
    CubeScene,
    holding_writer_lock,
    make_cube_scene,
    run_gdt,
    write_cube_workflow,
    write_points_ply,
)
from .twin_compare import assert_same_twins, layer_digests

RESCAN = "  - id: E2\n    role: as-is\n    inputs: [{path: scan2.ply, name: scan}]\n"


def _three_epochs(scene: CubeScene, twin: str, name: str) -> Path:
    """The cube workflow with a third epoch: the scene scanned again with fresh noise."""
    path = write_cube_workflow(scene, twin=twin, name=name)
    path.write_text(path.read_text().replace("stages:\n", RESCAN + "stages:\n", 1))
    return path


def _tree(twin: Path) -> dict[str, str]:
    return {p.relative_to(twin).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(twin.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory, registry) -> Path:
    """A cube scene whose twin holds E0 and E1, a three-epoch workflow over it, and that workflow's one-shot twin
    (``oneshot``): each case appends E2 to a copy."""
    scene = make_cube_scene(tmp_path_factory.mktemp("append") / "scene", n_cube=1500, n_new=300)
    pts = np.asarray(o3d.io.read_point_cloud(str(scene.scan)).points)
    write_points_ply(scene.dir / "scan2.ply", pts + np.random.default_rng(2).normal(0, 0.002, pts.shape))
    run_workflow(write_cube_workflow(scene), registry=registry)
    run_workflow(_three_epochs(scene, "oneshot", "oneshot.yaml"), registry=registry)
    _three_epochs(scene, "twin", "grow.yaml")
    return scene.dir


def _copy(template: Path, where: Path) -> Path:
    shutil.copytree(template, where)
    return where


def _complete(twin: Path, epochs: list[str]) -> None:
    store = TwinStore.open(twin)
    assert store.epochs() == epochs
    store.verify()
    assert store.run_lock_problems() == []
    lock = json.loads((twin / "gdt.lock").read_text())
    assert [e["id"] for e in lock["epochs"]] == epochs


def test_a_kill_at_every_step_of_an_append_keeps_a_complete_twin(template: Path, tmp_path: Path, registry) -> None:
    scenes = {case: _copy(template, tmp_path / case) for case in FAULT_STEPS}
    before = layer_digests(template / "twin")

    def killed(case: str) -> tuple[str, int, str]:
        env = {**os.environ, "GDT_FAULT": case, **({"GDT_RENAME_EXCHANGE": "0"} if case == "between-renames"
                                                   else {})}
        proc = subprocess.run([str(GDT), "run", str(scenes[case] / "grow.yaml"), "-q", "--no-report"], env=env,
                              capture_output=True, timeout=120)
        return case, proc.returncode, proc.stderr.decode(errors="replace")

    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(killed, FAULT_STEPS))
    for case, code, err in results:
        assert code == -signal.SIGKILL, (case, code, err)
        twin = scenes[case] / "twin"
        if case != "between-renames":  # that window leaves the old twin aside; the next run puts it back
            swapped = case in ("after-exchange", "old-renamed", "old-half-removed", "old-removed")
            _complete(twin, ["E0", "E1", "E2"] if swapped else ["E0", "E1"])
            kept = layer_digests(twin)
            assert {k: v for k, v in kept.items() if k in before} == before, case
        run_workflow(scenes[case] / "grow.yaml", registry=registry)
        _complete(twin, ["E0", "E1", "E2"])
        assert_same_twins(template / "oneshot", twin)
        assert [p.name for p in scenes[case].iterdir() if p.name.startswith(".twin.")] == [".twin.lock"], case


def test_a_second_append_is_refused_with_the_holders_pid(template: Path, tmp_path: Path) -> None:
    scene = _copy(template, tmp_path / "scene")
    before = _tree(scene / "twin")
    with holding_writer_lock(scene / "twin") as holder:
        res = run_gdt("run", str(scene / "grow.yaml"), "-q")
    assert res.returncode == 1 and f"pid {holder.pid}" in res.stderr, res.stderr
    assert _tree(scene / "twin") == before


def test_a_changed_held_epoch_is_an_error_that_names_it_and_leaves_the_twin(template: Path, tmp_path: Path) -> None:
    scene = _copy(template, tmp_path / "scene")
    before = _tree(scene / "twin")
    changed = scene / "changed.yaml"
    changed.write_text((scene / "grow.yaml").read_text().replace("sigma: 0.002", "sigma: 0.003"))
    for args in (("run", str(changed)), ("validate", str(changed), "--twin", str(scene / "twin"))):
        res = run_gdt(*args)
        err = " ".join(res.stderr.split()) + " ".join(res.stdout.split())
        assert res.returncode == 1, (args, res.stdout, res.stderr)
        assert "epoch E1" in err and "parameter sigma is 0.003 in the workflow, 0.002 in the twin" in err, err
        assert "--from E1" in err and "Traceback" not in err
    (scene / "scan.ply").write_bytes((scene / "scan.ply").read_bytes() + b"\n")  # same path, other bytes
    res = run_gdt("run", str(scene / "grow.yaml"))
    assert res.returncode == 1 and "epoch E1" in res.stderr and "scan.ply has sha256" in " ".join(res.stderr.split())
    res = run_gdt("run", str(scene / "grow.yaml"), "--from", "E7")
    assert res.returncode == 1 and "--from E7: no such epoch" in " ".join(res.stderr.split()), res.stderr
    assert _tree(scene / "twin") == before


def test_gdt_add_appends_a_scan_as_the_workflow_epoch_would(template: Path, tmp_path: Path) -> None:
    scene = _copy(template, tmp_path / "scene")
    (scene / "scan.ply").unlink()  # the earlier epochs' files are not needed
    (scene / "cad.obj").unlink()
    res = run_gdt("add", str(scene / "twin"), str(scene / "scan2.ply"), "--name", "scan", "-q", "--no-report")
    assert res.returncode == 0, res.stderr
    assert "added epoch E2" in res.stdout
    assert_same_twins(scene / "oneshot", scene / "twin")
    prov = TwinStore.open(scene / "twin").provenance("E2")
    assert "written by `gdt add`" in prov["workflow"]["text"] and "scan2.ply" in prov["workflow"]["text"]
    res = run_gdt("add", str(scene / "twin"), str(scene / "scan2.ply"), "--id", "E2")
    assert res.returncode == 1 and "--id E2: the twin already holds it" in res.stderr


def test_from_an_epoch_keeps_the_layers_before_it_and_rebuilds_the_rest(template: Path, tmp_path: Path,
                                                                        registry) -> None:
    scene = _copy(template, tmp_path / "scene")
    run_workflow(scene / "grow.yaml", registry=registry)
    e0 = {k: v for k, v in layer_digests(scene / "twin").items() if k.startswith("epochs/E0.")}
    (scene / "cad.obj").unlink()  # the kept epoch's input is not needed
    result = run_workflow(scene / "grow.yaml", registry=registry, from_epoch="E1")
    assert result.kept == ["E0"] and result.replaced == ["E1", "E2"] and [s.id for s in result.epochs] == ["E1",
                                                                                                          "E2"]
    assert {k: v for k, v in layer_digests(scene / "twin").items() if k.startswith("epochs/E0.")} == e0
    _complete(scene / "twin", ["E0", "E1", "E2"])
    assert_same_twins(template / "oneshot", scene / "twin")
