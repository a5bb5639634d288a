"""`gdt eval` end to end on a small fuselage scene: tables, JSON and a report with plots, scored on ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from gdt_pipeline.cli import cli
from gdt_pipeline.evaluation import evaluate, format_table, missing_scene
from gdt_pipeline.simulation import make_fuselage_scene

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def small_fuselage(tmp_path_factory) -> Path:
    """The fuselage scene at a low density, and fuselage.yaml pointed at it (fewer calibration samples)."""
    root = tmp_path_factory.mktemp("fuselage")
    data = root / "data"
    make_fuselage_scene(data, seed=0, points_per_m2=6000, web_points_per_m2=8000)
    wf = yaml.safe_load((ROOT / "workflows" / "fuselage.yaml").read_text())
    wf["twin"] = str(root / "twin")
    for epoch in wf["epochs"]:
        for inp in epoch["inputs"]:
            inp["path"] = str(data / Path(inp["path"]).name)
    for stage in wf["stages"]:
        if stage["uses"] == "calibrated_threshold":
            stage["with"]["samples"] = 5000
        for part in stage.get("with", {}).get("parts", []):
            part["path"] = str(data / Path(part["path"]).name)
    path = root / "fuselage.yaml"
    path.write_text(yaml.safe_dump(wf, sort_keys=False))
    return path


def test_eval_scores_the_workflow_and_the_peers_against_the_truth(small_fuselage: Path) -> None:
    peers = ("c2c", "m3c2") if pytest.importorskip("py4dgeo") else ("c2c",)
    result, arrays = evaluate(small_fuselage, peers=peers)
    (row,) = result["epochs"]
    # in the workflow's order (s0 … s33), not the file names' (s10 before s2)
    scans = sorted(small_fuselage.parent.glob("data/scan_E1_s*_truth.npz"),
                   key=lambda p: int(p.name.split("_s")[1].split("_")[0]))
    truth = np.concatenate([np.load(p)["changed"] for p in scans])
    assert row["points"] == len(truth) and row["changed"] == int(truth.sum()) > 0
    by = {m["name"]: m for m in row["methods"]}
    assert {"gdt", "c2c_fixed", "c2c_best", "m3c2_default", "m3c2_best"} <= set(by)
    # the twin's own masks, recounted here from the arrays the report gets
    gdt = arrays["E1"]["methods"]["gdt"]["changed"]
    assert by["gdt"]["tp"] == int(np.sum(gdt & truth)) and by["gdt"]["fp"] == int(np.sum(gdt & ~truth))
    assert by["gdt"]["f1"] > 0.95  # sub-millimetre scan, brackets 5 cm off the CAD: this workflow must nail it
    # the best-threshold sweep is an upper bound of the fixed threshold by construction
    assert by["c2c_best"]["f1"] >= by["c2c_fixed"]["f1"]
    assert by["m3c2_best"]["f1"] >= by["m3c2_default"]["f1"]
    brackets = [o for o in row["objects"] if o["truth"] == "new"]
    assert len(brackets) == 5
    assert sum(o["methods"]["gdt"]["found"] for o in brackets if o["points"]) >= 4
    assert all(o["methods"]["gdt"]["centre_error_mm"] < 5 for o in brackets if o["methods"]["gdt"]["found"])
    removal = row["removal"]
    assert removal["removed_in_view"] > 0
    # the reverse C2C peer finds the removed bracket (not all its facets: the plate's lie within 1 cm of the frame
    # web) but also "removes" much of what no station saw
    assert removal["objects"]["bracket_removed"]["c2c_reverse"]["found"]
    assert removal["methods"]["c2c_reverse"]["false_removal_rate_occluded"] > 0.3
    # the region of view finds it too and keeps what no station saw (far fewer false removals)
    assert removal["objects"]["bracket_removed"]["gdt"]["found"]
    assert removal["methods"]["gdt"]["false_removal_rate_occluded"] < 0.1
    assert row["composite"]["p95_mm"] < 1.0  # the composite keeps the exact CAD where nothing changed
    text = format_table(result)
    assert "gdt (this workflow)" in text and "M3C2" in text and "bracket_new_1" in text


def test_eval_command_writes_json_and_a_report_with_plots(small_fuselage: Path, tmp_path: Path) -> None:
    out = tmp_path / "report"
    res = CliRunner().invoke(cli, ["eval", str(small_fuselage), "--peers", "c2c", "--json",
                                   str(tmp_path / "r.json"), "--report", str(out)])
    assert res.exit_code == 0, res.output
    result = json.loads((tmp_path / "r.json").read_text())
    assert json.loads((out / "result.json").read_text()) == result
    report = (out / "report.md").read_text()
    for m in result["epochs"][0]["methods"]:
        assert m["label"] in report
    from matplotlib.image import imread

    for name in ("f1.png", "hist_E1.png", "map_E1.png"):
        img = imread(out / name)
        assert img.shape[0] > 100 and img.shape[1] > 100
        assert len(np.unique(img.reshape(-1, img.shape[-1]), axis=0)) > 3  # not blank
    assert "![change map E1](map_E1.png)" in report


def test_missing_scene_names_the_generator(tmp_path: Path) -> None:
    wf = yaml.safe_load((ROOT / "workflows" / "fuselage.yaml").read_text())
    wf["epochs"][0]["inputs"][0]["path"] = "fuselage/cad_skin.obj"
    path = tmp_path / "w.yaml"
    path.write_text(yaml.safe_dump(wf))
    assert missing_scene(path) == ("fuselage", tmp_path / "fuselage")


def test_fusion_override_writes_a_variant_beside_the_workflow(small_fuselage: Path) -> None:
    from gdt_pipeline.evaluation import with_fusion

    variant = with_fusion(small_fuselage, "replace_in_view")
    try:
        doc = yaml.safe_load(variant.read_text())
        assert variant.parent == small_fuselage.parent
        assert [s["uses"] for s in doc["stages"]][-1] == "replace_in_view"
        assert doc["twin"].endswith("_replace_in_view")
    finally:
        variant.unlink()
