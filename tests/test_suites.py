"""The random scene suite and ``gdt eval --suite``: same seed, same files; truth that agrees with the geometry
(removed facets only on removed or moved parts, visible fractions in [0, 1], occlusion lowers them, the simulator's
hits land where the truth says a station sees); and one small scene scored end to end through the command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from gdt_pipeline.cli import cli
from gdt_pipeline.cli.lab_commands import SUITES as CLI_SUITES
from gdt_pipeline.evaluation.metrics import prf
from gdt_pipeline.evaluation.suite import scene_seed
from gdt_pipeline.evaluation.suite_report import summarise
from gdt_pipeline.evaluation.suite_scoring import weighted_prf
from gdt_pipeline.runner import read_dataset
from gdt_pipeline.simulation import suite as suite_mod
from gdt_pipeline.simulation.scanner import ScannerSpec
from gdt_pipeline.simulation.suite import SUITES, make_suite_scene
from gdt_pipeline.simulation.suite_layout import draw_layout
from gdt_pipeline.simulation.suite_shapes import box, rectangles_overlap
from gdt_pipeline.simulation.suite_truth import cad_facet_truth
from gdt_pipeline.workflow import load_workflow

SEED = 31  # tests only: the published figures use other seeds


def _files(root: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(root.iterdir()) if p.is_file()}


@pytest.fixture(scope="module")
def mesh_scene(tmp_path_factory):
    """A precise-mesh scene (the suite that exercises the most: meshes, per-facet truth, Poisson)."""
    return make_suite_scene("precise-mesh", tmp_path_factory.mktemp("mesh"), SEED)


@pytest.fixture(scope="module")
def tof_scene(tmp_path_factory):
    """A ToF point scene."""
    return make_suite_scene("tof", tmp_path_factory.mktemp("tof"), SEED)


def test_the_same_seed_writes_the_same_files(mesh_scene, tmp_path: Path) -> None:
    again = make_suite_scene("precise-mesh", tmp_path / "again", SEED)
    first, second = _files(mesh_scene.root), _files(again.root)
    assert first.keys() == second.keys() and {"workflow.yaml", "truth_E1.npz", "sensor.yaml"} <= first.keys()
    assert [n for n in first if first[n] != second[n]] == []
    other = make_suite_scene("precise-mesh", tmp_path / "other", SEED + 1)
    assert _files(other.root)["truth_E1.npz"] != first["truth_E1.npz"]


def test_the_cli_knows_every_suite_and_scene_seeds_are_independent() -> None:
    assert set(CLI_SUITES) == set(SUITES)
    seeds = {scene_seed(s, k) for s in (1000, 1001) for k in range(20)}
    assert len(seeds) == 40 and scene_seed(1000, 3) == scene_seed(1000, 3)


@pytest.mark.parametrize("seed", range(6))
def test_layouts_do_not_overlap_and_draw_the_changes_asked_for(seed: int) -> None:
    lay = draw_layout(np.random.default_rng(seed), 1.5, 0.01)
    states = list(lay.states.values())
    assert 6 <= len(lay.cad) <= 14
    assert 1 <= states.count("removed") <= 2 and 1 <= states.count("moved") <= 2 and 1 <= states.count("new") <= 3
    for parts in (lay.cad, lay.asis):
        rects = [p.rect for p in parts.values()]
        assert not any(rectangles_overlap(a, b) for i, a in enumerate(rects) for b in rects[i + 1:])
    for part in [*lay.cad.values(), *lay.asis.values()]:
        assert part.mesh.is_watertight and part.mesh.is_winding_consistent and part.mesh.volume > 0
    assert len(lay.floor.faces) == 12  # the floor's top is two big triangles, as CAD has it
    for name, d in lay.displacements.items():
        assert np.allclose(lay.asis[name].mesh.center_mass - lay.cad[name].mesh.center_mass, d)


def test_truth_removed_facets_belong_to_removed_or_moved_parts(tof_scene) -> None:
    t = np.load(tof_scene.truth)
    states = json.loads(str(t["objects"]))
    displaced = json.loads(str(t["displacements"]))
    assert set(displaced) == {n for n, s in states.items() if s == "moved"}
    for name in (k[len("area__"):] for k in t.files if k.startswith("area__")):
        vis, vis_rem, removed = t[f"visible__{name}"], t[f"visible_removed__{name}"], t[f"removed__{name}"]
        assert ((vis >= 0) & (vis <= 1)).all() and (vis_rem <= vis + 1e-12).all()
        if states[name] == "removed":
            assert removed.all()
        elif states[name] == "unchanged":
            assert not removed.any() and not vis_rem.any()
    # unchanged parts: the simulator's hits land on facets the truth says a station sees (but for slivers of small
    # facets, a cylinder cap's wedge, that none of its few area samples caught)
    for k in range(len(tof_scene.scans)):
        s = np.load(tof_scene.root / f"scan_E1_s{k}_truth.npz")
        names = [str(n) for n in s["object_names"]]
        for name in (n for n, st in states.items() if st == "unchanged"):
            hit = s["facet_id"][s["object_id"] == names.index(name)]
            assert (t[f"visible__{name}"][hit] > 0).mean() > 0.98, name
        # points on new parts are changed, but for those within the tolerance of the CAD (the floor they stand on)
        new = np.isin(np.array(names)[s["object_id"]], [n for n, st in states.items() if st == "new"])
        assert s["changed"][new].mean() > 0.95
        assert not s["changed"][np.array(names)[s["object_id"]] == "floor"].any()


def test_mesh_scans_carry_per_facet_truth_the_reader_keeps(mesh_scene, registry) -> None:
    for path in mesh_scene.scans:
        t = np.load(path.with_name(path.stem + "_truth.npz"))
        ds = read_dataset(path, registry, name="scan", kind="mesh")
        assert len(ds.faces) == len(t["facet_changed"]) == len(t["facet_area"])
        assert ((t["facet_changed"] >= 0) & (t["facet_changed"] <= 1)).all() and (t["facet_area"] > 0).all()
        assert 0.02 < np.average(t["facet_changed"], weights=t["facet_area"]) < 0.6
        assert np.average(t["facet_offset"] < 0.005, weights=t["facet_area"]) > 0.95  # no invented membranes
    wf = load_workflow(mesh_scene.workflow, registry)
    assert [len(e.inputs) for e in wf.model.epochs] == [len(mesh_scene.cad), len(mesh_scene.scans)]
    assert (mesh_scene.root / "scan_E1_s0_pose.json").is_file() == mesh_scene.pose_files


def test_a_part_hidden_behind_another_is_less_visible_than_one_in_the_open() -> None:
    floor = box((6.0, 6.0, 0.02))
    floor.apply_translation((0, 0, -0.02))
    front, hidden, open_ = box((0.8, 0.3, 0.6)), box((0.3, 0.3, 0.3)), box((0.3, 0.3, 0.3))
    front.apply_translation((0.0, -0.5, 0.0))
    hidden.apply_translation((0.0, 0.2, 0.0))
    open_.apply_translation((1.2, 0.2, 0.0))
    eye = np.array([0.0, -3.0, 0.3])
    station = [(eye, np.array([0.6, 0.0, 0.2]), ScannerSpec(fov_deg=70.0, max_range=10.0))]
    asis = [floor, front, hidden, open_]
    rng = np.random.default_rng(0)
    vis = {name: cad_facet_truth(mesh, "unchanged", station, asis, rng) for name, mesh in
           (("hidden", hidden), ("open", open_))}

    def facing(mesh: trimesh.Trimesh) -> np.ndarray:
        return mesh.face_normals @ np.array([0.0, -1.0, 0.0]) > 0.9

    hidden_face = vis["hidden"]["visible"][facing(hidden)]
    open_face = vis["open"]["visible"][facing(open_)]
    assert hidden_face.max() == 0.0 and open_face.min() == 1.0
    share = {k: np.average(v["visible"], weights=v["area"]) for k, v in vis.items()}
    assert share["hidden"] < 0.1 < share["open"]
    # without the part in front, the hidden one's face is seen: occlusion, not the frustum, hid it
    alone = cad_facet_truth(hidden, "unchanged", station, [floor, hidden], rng)
    assert alone["visible"][facing(hidden)].min() == 1.0


def test_weighted_scores_are_the_plain_ones_for_points_and_summaries_take_mean_and_worst() -> None:
    rng = np.random.default_rng(0)
    truth, pred = rng.random(500) < 0.3, rng.random(500) < 0.35
    plain, weighted = prf(pred, truth), weighted_prf(pred, truth)
    assert weighted["f1"] == pytest.approx(plain["f1"]) and weighted["precision"] == pytest.approx(plain["precision"])
    # a facet half changed, flagged: half a true positive and half a false one, by its area
    half = weighted_prf(np.array([True]), np.array([0.5]), np.array([2.0]))
    assert half["precision"] == pytest.approx(0.5) and half["recall"] == pytest.approx(1.0)
    rows = [{"methods": {"gdt": {"f1": f}}, "removal": {"methods": {"gdt": {"recall": r, "false_removals": x}}}}
            for f, r, x in ((0.9, 1.0, 0.0), (0.7, 0.5, 0.02), (0.8, None, 0.01))]
    s = summarise(rows)["gdt"]
    assert s["f1"]["mean"] == pytest.approx(0.8) and s["f1"]["worst"] == 0.7
    assert s["removal"] == {"mean": 0.75, "worst": 0.5, "n": 2}
    assert s["false"]["worst"] == 0.02


def test_eval_suite_scores_a_small_scene_end_to_end(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(suite_mod, "POINT_BUDGET", (20_000, 25_000))  # a tiny scene: the test's time, not the truth
    out = tmp_path / "suite_spec"
    res = CliRunner().invoke(cli, ["eval", "--suite", "precise", "--scenes", "1", "--seed", str(SEED), "--peers",
                                   "c2c", "--out", str(out), "--json", str(tmp_path / "r.json")])
    assert res.exit_code == 0, res.output
    result = json.loads((tmp_path / "r.json").read_text())
    assert result == json.loads((out / "results.json").read_text())
    (row,) = result["rows"]
    assert row["seed"] == scene_seed(SEED, 0) and 15_000 < row["elements"] == row["points"] < 30_000
    m = row["methods"]
    assert set(m) == {"gdt", "c2c_fixed", "c2c_best"}
    # a sub-millimetre scan of parts moved by millimetres to decimetres: distances alone nearly nail it with the
    # best τ, and the default workflow must be close
    assert m["c2c_best"]["f1"] >= max(0.95, m["c2c_fixed"]["f1"])
    assert m["gdt"]["f1"] > 0.9
    rem = row["removal"]
    assert rem["removed_visible_area_m2"] > 0 and rem["unchanged_visible_area_m2"] > rem["removed_visible_area_m2"]
    for method in ("gdt", "c2c_reverse"):
        r = rem["methods"][method]
        assert 0 <= r["recall"] <= 1 and 0 <= r["false_removals"] <= 1
    assert rem["methods"]["gdt"]["false_removals"] < 0.05
    # one scene: the mean and the worst are that scene's figures
    s = result["summary"]
    assert s["gdt"]["f1"]["mean"] == s["gdt"]["f1"]["worst"] == m["gdt"]["f1"]
    assert s["c2c_reverse"]["removal"]["mean"] == rem["methods"]["c2c_reverse"]["recall"]
    assert "| **gdt (default workflow)** |" in (out / "results.md").read_text()
    assert "suite 'precise': 1 scene(s)" in res.output
