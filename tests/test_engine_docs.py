"""The plugin examples of docs/engine.md run as written: each section's Python block becomes a module, its
entry-point line names that module, and a real workflow on the cube scene uses the stage it adds."""

from __future__ import annotations

import importlib.util
import json
import re
import sys
import tomllib
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from .conftest import REPO, CubeScene, write_cube_workflow

DOC = REPO / "docs" / "engine.md"


def _section(title: str) -> str:
    text = DOC.read_text(encoding="utf-8")
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end if end >= 0 else None]


def _blocks(section: str, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", section, flags=re.S)


def _plugin(title: str, tmp_path: Path) -> tuple[str, ModuleType]:
    """The section's one Python block as a module under the name its one entry-point line gives."""
    section = _section(title)
    [code] = _blocks(section, "python")
    [toml] = _blocks(section, "toml")
    [(name, target)] = tomllib.loads(toml)["project"]["entry-points"]["gdt_pipeline"].items()
    path = tmp_path / f"{target}.py"
    path.write_text(code, encoding="utf-8")
    spec = importlib.util.spec_from_file_location(target, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[target] = module  # as an installed plugin would be
    spec.loader.exec_module(module)
    return name, module


def _registry(title: str, tmp_path: Path):
    from gdt_pipeline.plugins import load_registry

    name, module = _plugin(title, tmp_path)
    return load_registry(blocked=(), extra=[(name, module)])


def _primvars(twin: Path, *names: str) -> list[np.ndarray]:
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(twin / "twin.usda"))
    pv = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Twin/E1_scan"))
    return [np.asarray(pv.GetPrimvar(f"gdt:{n}").Get(), dtype=np.float64) for n in names]


def _stage_report(twin: Path, uses: str) -> dict:
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(twin / "epochs" / "E1.usdc"))
    prov = json.loads(layer.customLayerData["gdt"]["provenance_json"])
    return next(s for s in prov["stages"] if s["uses"] == uses)


def _calibrated(wf: Path) -> None:
    wf.write_text(wf.read_text().replace("  - uses: fixed\n    role: as-is\n    with: {tau: 10.0}\n",
                                         "  - uses: calibrated_threshold\n    role: as-is\n"
                                         "    with: {false_alarm: 0.01, samples: 20000}\n"))


def test_distance_measure_example(cube_scene: CubeScene, tmp_path: Path) -> None:
    from gdt_pipeline.runner import run_workflow

    registry = _registry("Adding a distance measure", tmp_path)
    assert registry.get("mahalanobis").family == "distance"
    # the same scene scored by hotelling: T² is the square of the Mahalanobis distance
    wf_t2 = write_cube_workflow(cube_scene, twin="twin_t2", distance="hotelling", name="t2.yaml")
    wf = write_cube_workflow(cube_scene, twin="twin_md", distance="mahalanobis", name="md.yaml")
    _calibrated(wf)
    [t2] = _primvars(run_workflow(wf_t2, registry=registry).twin, "changeScore")
    twin = run_workflow(wf, registry=registry).twin
    score, state = _primvars(twin, "changeScore", "changeState")
    np.testing.assert_allclose(score**2, t2, rtol=1e-5)
    # calibrated_threshold took it (the null simulator comes with distance_stage) and finds the new box
    [cal] = _stage_report(twin, "calibrated_threshold")["report"]["calibration"]
    assert cal["false_alarm_achieved"] == pytest.approx(0.01, rel=0.3)
    flagged, truth = state == 1, cube_scene.changed
    assert 2 * np.sum(flagged & truth) / (flagged.sum() + truth.sum()) > 0.95


def test_stage_family_member_example(cube_scene: CubeScene, tmp_path: Path) -> None:
    from gdt_pipeline.runner import run_workflow

    registry = _registry("Adding a stage family member", tmp_path)
    assert registry.get("robust_threshold").family == "threshold"
    wf = write_cube_workflow(cube_scene, distance="euclidean")
    wf.write_text(wf.read_text().replace("uses: fixed\n    role: as-is\n    with: {tau: 10.0}",
                                         "uses: robust_threshold\n    role: as-is\n    with: {k: 5.0}"))
    twin = run_workflow(wf, registry=registry).twin
    score, state = _primvars(twin, "changeScore", "changeState")
    [tau] = _stage_report(twin, "robust_threshold")["report"]["tau"]
    finite = score[np.isfinite(score)]
    median = np.median(finite)
    assert tau == pytest.approx(median + 5.0 * 1.4826 * np.median(np.abs(finite - median)), rel=1e-4)
    assert 0.002 < tau < 0.02  # a few σ of the 2 mm scan noise, far below the new box's 0.35 m
    np.testing.assert_array_equal(state == 1, ~(score <= np.float32(tau)))
    flagged, truth = state == 1, cube_scene.changed
    assert 2 * np.sum(flagged & truth) / (flagged.sum() + truth.sum()) > 0.95
