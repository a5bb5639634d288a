"""Issue 35: a twin that grows. E0 followed by one append per epoch gives, bit for bit, the twin one run of all the
epochs gives (the paper's four-epoch test scene; a ToF family scene with three as-is epochs); an append needs none
of the earlier epochs' files, leaves every earlier layer byte for byte, and ``gdt audit --epoch`` re-runs one epoch
from the twin alone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from gdt_pipeline.audit import audit_twin
from gdt_pipeline.runner import run_workflow
from gdt_pipeline.simulation import make_paper_test_scene
from gdt_pipeline.simulation.suite import make_suite_scene

from .conftest import write_points_ply
from .twin_compare import assert_same_twins, layer_digests

# fewer null draws than the shipped workflow (50 000) keep the module's six runs short; equality does not depend on it
SAMPLES = 4000
THIN = 1 / 30


def _workflow(scene: Path, data: dict, epochs: int, twin: str, name: str) -> Path:
    """The workflow ``data`` with its first ``epochs`` epochs only (stage entries keep their places in the file,
    so every stage keeps its index and seed) into ``twin``."""
    out = dict(data, twin=twin, epochs=data["epochs"][:epochs])
    ids = {e["id"] for e in out["epochs"]}
    out["stages"] = [dict(st, epochs=[e for e in st["epochs"] if e in ids]) if "epochs" in st else st
                     for st in data["stages"]]
    path = scene / name
    path.write_text(yaml.safe_dump(out, sort_keys=False), encoding="utf-8")
    return path


def _grown(scene: Path, data: dict, registry) -> tuple[Path, dict, dict]:
    """E0, then one append per epoch into ``grown``: the twin, the sha256 of every file before the last append and
    after it. The earlier epochs' inputs are deleted before the last append."""
    n = len(data["epochs"])
    for k in range(1, n):
        run_workflow(_workflow(scene, data, k, "grown", f"grow_{k}.yaml"), registry=registry)
    before = layer_digests(scene / "grown")
    for epoch in data["epochs"][:-1]:
        for inp in epoch["inputs"]:
            (scene / inp["path"]).unlink()
    result = run_workflow(_workflow(scene, data, n, "grown", "grow_all.yaml"), registry=registry)
    assert result.kept == [e["id"] for e in data["epochs"][:-1]] and [s.id for s in result.epochs] == \
        [data["epochs"][-1]["id"]]
    return scene / "grown", before, layer_digests(scene / "grown")


@pytest.fixture(scope="module")
def paper(tmp_path_factory: pytest.TempPathFactory, registry) -> tuple[Path, dict]:
    """The paper's test scene with the shipped workflow (fewer null draws), its one-shot twin in ``oneshot``."""
    scene = tmp_path_factory.mktemp("paper")
    make_paper_test_scene(scene / "data", seed=0)
    data = yaml.safe_load((Path(__file__).parents[1] / "workflows" / "test_scene.yaml").read_text())
    for epoch in data["epochs"]:
        for inp in epoch["inputs"]:
            inp["path"] = inp["path"].replace("data/paper_test_scene/", "data/")
    for st in data["stages"]:
        if st["uses"] == "calibrated_threshold":
            st["with"] = {**st["with"], "samples": SAMPLES}
    run_workflow(_workflow(scene, data, 4, "oneshot", "oneshot.yaml"), registry=registry)
    return scene, data


def test_appends_equal_the_one_shot_run_on_the_paper_scene_without_the_old_inputs(paper, registry) -> None:
    scene, data = paper
    grown, before, after = _grown(scene, data, registry)
    assert_same_twins(scene / "oneshot", grown)
    assert {k: v for k, v in after.items() if k in before} == before  # earlier layers and payloads untouched
    assert set(after) - set(before) == {"epochs/E3.usdc"}
    # audit of the last epoch: from the twin's composite at E2 and E3's own inputs; E0-E2's files are gone
    report = audit_twin(grown, epoch="E3", registry=registry)
    assert [(e.epoch, e.verdict, e.exact, e.cache_keys_match) for e in report.epochs] == [("E3", "match", True,
                                                                                          True)]


def _tof_three_epochs(scene: Path, seed: int) -> dict:
    """A ToF family scene (CAD, then a scan) with two more as-is epochs: the scene rescanned, each scan thinned to
    a 30th and given fresh noise of the scan's own order (scan against scan, Bhattacharyya integrates the
    neighbours' mixtures: thin scans keep the module short)."""
    made = make_suite_scene("tof", scene, seed)
    data = yaml.safe_load(made.workflow.read_text())
    rng = np.random.default_rng(seed)
    import open3d as o3d

    for epoch_id in ("E2", "E3"):
        inputs = []
        for inp in data["epochs"][1]["inputs"]:
            pts = np.asarray(o3d.io.read_point_cloud(str(scene / inp["path"])).points)
            keep = rng.random(len(pts)) < THIN
            path = inp["path"].replace("_E1_", f"_{epoch_id}_")
            write_points_ply(scene / path, pts[keep] + rng.normal(0, 0.002, (int(keep.sum()), 3)))
            inputs.append({**inp, "path": path})
        data["epochs"].append({"id": epoch_id, "role": "as-is", "inputs": inputs})
    for epoch in data["epochs"][1:2]:  # E1 thinned alike, so that the module stays short
        for inp in epoch["inputs"]:
            pts = np.asarray(o3d.io.read_point_cloud(str(scene / inp["path"])).points)
            write_points_ply(scene / inp["path"], pts[rng.random(len(pts)) < THIN])
    for st in data["stages"]:
        if st["uses"] == "calibrated_threshold":
            st["with"] = {**st["with"], "samples": SAMPLES}
    return data


def test_appends_equal_the_one_shot_run_on_a_tof_scene_with_three_as_is_epochs(tmp_path: Path, registry) -> None:
    data = _tof_three_epochs(tmp_path, seed=35)
    run_workflow(_workflow(tmp_path, data, 4, "oneshot", "oneshot.yaml"), registry=registry)
    grown, before, after = _grown(tmp_path, data, registry)
    assert_same_twins(tmp_path / "oneshot", grown)
    assert {k: v for k, v in after.items() if k in before} == before
