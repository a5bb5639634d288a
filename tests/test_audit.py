"""`gdt audit`: a fresh twin audits clean and bit-identical; a changed input byte, an edited stored score and a
plugin version mismatch are each caught with a clear message; moved inputs can be pointed to."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Vt

from gdt_pipeline.audit import audit_twin
from gdt_pipeline.runner import run_workflow
from twin_store import sha256_file

from .conftest import CubeScene, run_gdt, write_cube_workflow


@pytest.fixture
def twin(cube_scene: CubeScene, registry) -> Path:
    return run_workflow(write_cube_workflow(cube_scene), registry=registry).twin


def test_fresh_twin_audits_clean(twin: Path, tmp_path: Path) -> None:
    report_path = tmp_path / "audit.json"
    res = run_gdt("audit", str(twin), "--report", str(report_path))
    assert res.returncode == 0, res.stdout + res.stderr
    assert "E0: match (bit-identical)" in res.stdout and "E1: match (bit-identical)" in res.stdout
    report = json.loads(report_path.read_text())
    assert report["ok"] is True and [e["verdict"] for e in report["epochs"]] == ["match", "match"]
    assert all(e["exact"] and e["cache_keys_match"] for e in report["epochs"])
    res = run_gdt("audit", str(twin), "--epoch", "E0")
    assert res.returncode == 0 and "E1" not in res.stdout


def test_thread_count_does_not_change_the_twin(twin: Path) -> None:
    env = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    res = run_gdt("audit", str(twin), env=env)
    assert res.returncode == 0 and res.stdout.count("bit-identical") == 2, res.stdout


def test_one_changed_input_byte_fails(twin: Path, cube_scene: CubeScene) -> None:
    data = bytearray(cube_scene.scan.read_bytes())
    data[-3] = ord("7") if data[-3] != ord("7") else ord("8")
    cube_scene.scan.write_bytes(bytes(data))
    res = run_gdt("audit", str(twin))
    assert res.returncode == 1
    assert "E0: match" in res.stdout and "E1: INPUTS CHANGED" in res.stdout
    assert "input scan.ply has changed: sha256" in res.stdout and "audit FAILED" in res.stdout


def test_moved_inputs_are_reported_and_can_be_pointed_to(twin: Path, cube_scene: CubeScene, tmp_path: Path) -> None:
    moved = tmp_path / "moved"
    moved.mkdir()
    shutil.move(cube_scene.dir / "scan.ply", moved / "scan.ply")
    shutil.copy(cube_scene.cad, moved / "cad.obj")
    res = run_gdt("audit", str(twin))
    assert res.returncode == 1 and "input scan.ply is missing" in res.stdout
    res = run_gdt("audit", str(twin), "--inputs-dir", str(moved))
    assert res.returncode == 0 and "audit passed" in res.stdout, res.stdout


def _edit_layer(path: Path, fn) -> None:
    layer = Sdf.Layer.FindOrOpen(str(path))
    fn(layer)
    assert layer.Save()
    # A deliberate edit: the root's record of the layer's sha256 is made to follow it, so that these tests reach the
    # audit's own comparisons (an edit the record does not follow is refused before them: test_twin_safety).
    root = Sdf.Layer.FindOrOpen(str(path.parents[1] / "twin.usda"))
    data = dict(root.customLayerData)
    gdt = dict(data["gdt"])
    gdt["layer_sha256"] = {**gdt["layer_sha256"], f"epochs/{path.name}": sha256_file(path)}
    root.customLayerData = {**data, "gdt": gdt}
    assert root.Save()


def test_edited_stored_score_fails(twin: Path) -> None:
    def bump(layer: Sdf.Layer) -> None:
        attr = layer.GetAttributeAtPath("/Twin/E1_scan.primvars:gdt:changeScore")
        scores = np.array(attr.default, dtype=np.float32)
        scores[17] += 5.0
        attr.default = Vt.FloatArray.FromNumpy(scores)

    _edit_layer(twin / "epochs" / "E1.usdc", bump)
    report = audit_twin(twin)
    assert not report.ok and [e.verdict for e in report.epochs] == ["match", "differs"]
    [diff] = report.epochs[1].differences
    assert (diff.key, diff.field, diff.count, diff.first) == ("E1_scan", "score", 1, [17])
    res = run_gdt("audit", str(twin))
    assert res.returncode == 1 and "E1_scan.score: 1 element(s) differ, first [17]" in res.stdout


def test_version_mismatch_warns_and_strict_fails(twin: Path) -> None:
    def older(layer: Sdf.Layer) -> None:
        data = dict(layer.customLayerData)
        gdt = dict(data["gdt"])
        prov = json.loads(gdt["provenance_json"])
        prov["stages"][3]["plugin_version"] = "0.0.9"
        gdt["provenance_json"] = json.dumps(prov, sort_keys=True)
        data["gdt"] = gdt
        layer.customLayerData = data

    _edit_layer(twin / "epochs" / "E1.usdc", older)
    res = run_gdt("audit", str(twin))
    assert res.returncode == 0, res.stdout + res.stderr
    err = " ".join(res.stderr.split())
    assert "warning:" in err and "'bhattacharyya' was made with gdt-pipeline 0.0.9" in err
    res = run_gdt("audit", str(twin), "--strict")
    assert res.returncode == 1 and "audit FAILED" in res.stdout and "error:" in res.stderr


def test_log_prints_provenance(twin: Path) -> None:
    res = run_gdt("log", str(twin), "--provenance")
    assert res.returncode == 0 and "# epoch E1" in res.stdout and "cache_key:" in res.stdout
    assert "uses: bhattacharyya" in res.stdout and "sha256:" in res.stdout
