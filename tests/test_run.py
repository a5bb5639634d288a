"""End to end: a workflow runs into a twin; detection is checked against the generated ground truth; the twin,
its provenance and gdt.lock are read back; bad input ends in a clear error and leaves the twin untouched."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import types
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom

from gdt_pipeline import StageSpec, hookimpl
from gdt_pipeline.plugins import load_registry
from gdt_pipeline.runner import run_workflow

from .conftest import CubeScene, make_cube_scene, run_gdt, write_cube_workflow, write_points_ply


def _f1(pred: np.ndarray, truth: np.ndarray) -> float:
    tp = np.sum(pred & truth)
    return 2 * tp / (np.sum(pred) + np.sum(truth))


def _tree_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_cube_scene_end_to_end(cube_scene: CubeScene, registry) -> None:
    wf = write_cube_workflow(cube_scene)
    result = run_workflow(wf, registry=registry)
    twin = cube_scene.dir / "twin"
    assert result.twin == twin.resolve()
    assert sorted(p.name for p in (twin / "epochs").iterdir()) == ["E0.usdc", "E1.usdc"]
    assert not list(cube_scene.dir.glob(".twin.partial-*"))

    # read back with plain pxr: the composed twin after E1
    stage = Usd.Stage.Open(str(twin / "twin.usda"))
    assert list(stage.GetRootLayer().subLayerPaths) == ["epochs/E1.usdc", "epochs/E0.usdc"]
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0 and UsdGeom.GetStageUpAxis(stage) == "Z"
    scan = UsdGeom.Points(stage.GetPrimAtPath("/Twin/E1_scan"))
    cad = UsdGeom.Mesh(stage.GetPrimAtPath("/Twin/E0_cad"))
    assert scan and cad
    pv = UsdGeom.PrimvarsAPI(scan.GetPrim())
    state = np.asarray(pv.GetPrimvar("gdt:changeState").Get())
    pred = state == 1
    f1 = _f1(pred, cube_scene.changed)
    assert f1 > 0.97, f"F1 {f1:.3f}"
    assert pv.GetPrimvar("gdt:changeState").GetInterpolation() == UsdGeom.Tokens.vertex
    cov = pv.GetPrimvar("gdt:covariance")
    assert cov.GetElementSize() == 6
    np.testing.assert_allclose(np.asarray(cov.Get())[:6], [cube_scene.sigma**2, 0, 0, cube_scene.sigma**2, 0,
                                                          cube_scene.sigma**2], rtol=1e-6)
    pts = np.asarray(scan.GetPointsAttr().Get())
    assert len(pts) == len(cube_scene.changed)
    # the CAD keeps all its 12 facets visible and unchanged
    cad_pv = UsdGeom.PrimvarsAPI(cad.GetPrim())
    assert np.all(np.asarray(cad_pv.GetPrimvar("gdt:changeState").Get()) == 0)
    assert len(cad.GetHoleIndicesAttr().Get() or []) == 0

    # provenance in the epoch layer
    layer = Sdf.Layer.FindOrOpen(str(twin / "epochs" / "E1.usdc"))
    prov = json.loads(layer.customLayerData["gdt"]["provenance_json"])
    assert prov["epoch"] == {"id": "E1", "index": 1, "role": "as-is"}
    assert prov["inputs"][0]["sha256"] == hashlib.sha256(cube_scene.scan.read_bytes()).hexdigest()
    assert [s["uses"] for s in prov["stages"]] == ["identity", "constant", "nearest", "bhattacharyya", "fixed",
                                                   "keep_unchanged"]
    assert prov["stages"][4]["params"] == {"tau": 10.0}
    assert prov["counts"]["new"] == int(pred.sum())
    assert {"numpy", "usd-core", "open3d-cpu"} <= set(prov["packages"])

    # gdt.lock beside the layers
    lock = json.loads((twin / "gdt.lock").read_text())
    assert lock["seed"] == 7 and [e["id"] for e in lock["epochs"]] == ["E0", "E1"]
    keys = [s["cache_key"] for e in lock["epochs"] for s in e["stages"]]
    assert len(set(keys)) == len(keys) and all(len(k) == 64 for k in keys)


def test_same_workflow_same_twin_and_keys_follow_params(cube_scene: CubeScene, registry) -> None:
    a = run_workflow(write_cube_workflow(cube_scene, twin="a", name="a.yaml"), registry=registry)
    b = run_workflow(write_cube_workflow(cube_scene, twin="b", name="b.yaml"), registry=registry)
    c = run_workflow(write_cube_workflow(cube_scene, twin="c", name="c.yaml", tau=12.0), registry=registry)
    la, lb, lc = (json.loads(r.lock.read_text()) for r in (a, b, c))
    ka = [s["cache_key"] for s in la["epochs"][1]["stages"]]
    kb = [s["cache_key"] for s in lb["epochs"][1]["stages"]]
    kc = [s["cache_key"] for s in lc["epochs"][1]["stages"]]
    assert ka == kb
    assert ka[:4] == kc[:4] and ka[4] != kc[4] and ka[5] != kc[5]  # the threshold and everything downstream
    for epoch in ("E0", "E1"):
        la_ = Sdf.Layer.FindOrOpen(str(a.twin / "epochs" / f"{epoch}.usdc"))
        lb_ = Sdf.Layer.FindOrOpen(str(b.twin / "epochs" / f"{epoch}.usdc"))
        for spec_path in ("/Twin/E1_scan.primvars:gdt:changeScore", "/Twin/E0_cad.points"):
            va, vb = la_.GetAttributeAtPath(spec_path), lb_.GetAttributeAtPath(spec_path)
            if va is not None:
                assert np.array_equal(np.asarray(va.default), np.asarray(vb.default), equal_nan=True)


def test_sample_plugin_used_in_a_workflow(cube_scene: CubeScene) -> None:
    wf = write_cube_workflow(cube_scene, distance="c2c", tau=0.01)
    res = run_gdt("run", str(wf), "--quiet")
    assert res.returncode == 0, res.stderr
    assert "twin written to" in res.stdout
    layer = Sdf.Layer.FindOrOpen(str(cube_scene.dir / "twin" / "epochs" / "E1.usdc"))
    prov = json.loads(layer.customLayerData["gdt"]["provenance_json"])
    rec = next(s for s in prov["stages"] if s["uses"] == "c2c")
    assert rec["plugin"] == "gdt-c2c" and rec["entry_point"] == "c2c" and rec["family"] == "distance"
    stage = Usd.Stage.Open(str(cube_scene.dir / "twin" / "twin.usda"))
    state = np.asarray(UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Twin/E1_scan")).GetPrimvar("gdt:changeState").Get())
    assert _f1(state == 1, cube_scene.changed) > 0.97


@pytest.fixture(scope="module")
def written_twin(tmp_path_factory: pytest.TempPathFactory) -> CubeScene:
    """A cube scene with a twin written by `gdt run`, once for the module (the tests below get copies)."""
    scene = make_cube_scene(tmp_path_factory.mktemp("written") / "scene")
    res = run_gdt("run", str(write_cube_workflow(scene)), "--quiet")
    assert res.returncode == 0, res.stderr
    return scene


@pytest.fixture
def existing_twin(written_twin: CubeScene, tmp_path: Path) -> tuple[CubeScene, Path, dict[str, str]]:
    """A copy of the cube scene with its twin already written (paths in a twin are relative to it), and the digest
    of that twin's files."""
    root = tmp_path / "scene"
    shutil.copytree(written_twin.dir, root)
    scene = dataclasses.replace(written_twin, dir=root, cad=root / written_twin.cad.name,
                                scan=root / written_twin.scan.name)
    return scene, root / "workflow.yaml", _tree_digest(root / "twin")


def _assert_failed_cleanly(res, scene: CubeScene, digest: dict[str, str], *needles: str) -> None:
    assert res.returncode == 1, (res.stdout, res.stderr)
    err = " ".join(res.stderr.split())
    assert "Traceback" not in res.stderr
    for needle in needles:
        assert needle in err, err
    assert _tree_digest(scene.dir / "twin") == digest
    assert not [p for p in scene.dir.glob(".twin.*") if p.name != ".twin.lock"]


def test_missing_input_file(existing_twin) -> None:
    scene, wf, digest = existing_twin
    scene.scan.unlink()
    res = run_gdt("run", str(wf), "--overwrite")
    _assert_failed_cleanly(res, scene, digest, "input file not found", "scan.ply", "epochs.1.inputs.0.path")


def test_unreadable_mesh(existing_twin) -> None:
    scene, wf, digest = existing_twin
    scene.cad.write_bytes(b"\x00\x01 this is not a mesh \xff" * 10)
    res = run_gdt("run", str(wf), "--overwrite")
    _assert_failed_cleanly(res, scene, digest, "epoch E0, input 0", "cad.obj")


def test_nan_coordinates(existing_twin) -> None:
    scene, wf, digest = existing_twin
    pts = np.random.default_rng(1).normal(size=(50, 3))
    pts[[3, 17], 1] = np.nan
    write_points_ply(scene.scan, pts)
    res = run_gdt("run", str(wf), "--overwrite")
    _assert_failed_cleanly(res, scene, digest, "epoch E1, input 0", "scan.ply", "2 of 50 coordinates are NaN",
                           "[3, 17]")


def test_empty_cloud(existing_twin) -> None:
    scene, wf, digest = existing_twin
    write_points_ply(scene.scan, np.zeros((0, 3)))
    res = run_gdt("run", str(wf), "--overwrite")
    _assert_failed_cleanly(res, scene, digest, "epoch E1, input 0", "scan.ply")
    assert "empty" in res.stderr or "no points" in res.stderr


def test_a_run_on_a_twin_that_holds_every_epoch_changes_nothing(existing_twin) -> None:
    scene, wf, digest = existing_twin
    res = run_gdt("run", str(wf))
    assert res.returncode == 0, res.stderr
    assert "up to date" in " ".join(res.stdout.split()) and "kept 2 epochs" in res.stdout
    assert _tree_digest(scene.dir / "twin") == digest
    assert not [p for p in scene.dir.glob(".twin.*") if p.name != ".twin.lock"]


def test_stage_error_names_epoch_and_stage(existing_twin) -> None:
    scene, wf, digest = existing_twin
    text = wf.read_text().replace("with: {model: isotropic, sigma: 0.001}",
                                  "with: {model: box, half_widths: [0.001, 0.001, 0.001]}")
    wf.write_text(text.replace("uses: bhattacharyya", "uses: hotelling"))
    res = run_gdt("run", str(wf), "--overwrite")
    _assert_failed_cleanly(res, scene, digest, "epoch E1, stage 4 'hotelling' (gdt-pipeline", "'box'",
                           "holds only for normal distributions")
    debug = run_gdt("--debug", "run", str(wf), "--overwrite")
    assert debug.returncode == 1 and "Traceback" in debug.stderr


def _interrupting_module() -> types.ModuleType:
    from pydantic import BaseModel, ConfigDict

    class P(BaseModel):
        model_config = ConfigDict(extra="forbid")

    def run(ctx):
        raise KeyboardInterrupt

    mod = types.ModuleType("interrupting")

    @hookimpl
    def gdt_stages():
        return [StageSpec(name="interrupting", family="fusion", version="1", params=P, run=run,
                          requires=("recent",), provides=("composite",))]

    mod.gdt_stages = gdt_stages
    return mod


def test_interrupt_mid_run_keeps_the_old_twin(existing_twin) -> None:
    scene, wf, digest = existing_twin
    wf.write_text(wf.read_text().replace("  - uses: keep_unchanged\n",
                                         "  - uses: interrupting\n    epochs: [E1]\n  - uses: keep_unchanged\n"
                                         "    epochs: [E0]\n"))
    registry = load_registry(blocked=(), extra=[("interrupting", _interrupting_module())])
    with pytest.raises(KeyboardInterrupt):
        run_workflow(wf, registry=registry, overwrite=True)
    assert _tree_digest(scene.dir / "twin") == digest
    assert not [p for p in scene.dir.glob(".twin.*") if p.name != ".twin.lock"]
