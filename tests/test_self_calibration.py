"""Self-calibration of a sensor profile against the known scene: the EM fit recovers the scales of the range and
lateral terms from distances with changed points mixed in, and sensor_model fitted from the preset on a simulated
ToF scan of CAD boxes finds the true scanner's scales; with no mesh to calibrate against the prior stays."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from gdt_pipeline import Composite
from gdt_pipeline.sensors import PRESETS
from gdt_pipeline.simulation.scanner import ScannerSpec, simulate_scan
from gdt_pipeline.simulation.suite import scaled_profile
from stages.uncertainty.self_calibration import FitData, calibrate_profile
from stages.uncertainty.sensor_model import sensor_survey
from tests.rov_helpers import cad_item, plant_room, stage_ctx


def test_em_recovers_the_scales_with_a_fifth_of_the_points_changed() -> None:
    rng = np.random.default_rng(3)
    n = 40_000
    range_term = rng.uniform(1e-5, 4e-4, n)  # σ² of the prior's range terms along the normal
    lateral_term = rng.uniform(0.0, 5e-5, n)  # both terms matter: each scale is determined (seeds 0-4: ≤ 2 %)
    true_var = 0.5 ** 2 * range_term + 1.6 ** 2 * lateral_term
    distance = rng.normal(0.0, np.sqrt(true_var))
    changed = rng.random(n) < 0.2
    cutoff = 12 * np.sqrt(range_term + lateral_term)
    distance[changed] = rng.uniform(-cutoff[changed], cutoff[changed])
    data = FitData(distance, range_term, lateral_term, np.zeros(n), cutoff)
    found = calibrate_profile(PRESETS["tof_low_cost"], data, min_points=500, separate=True)
    assert found.range_scale == pytest.approx(0.5, rel=0.05)
    assert found.lateral_scale == pytest.approx(1.6, rel=0.05)
    assert found.record["outlier_share"] == pytest.approx(0.2, abs=0.03)
    assert found.profile.range_sigma == pytest.approx([c * found.range_scale for c in (0.002, 0.0, 0.008)])
    assert 0.95 < found.record["normalized_rms"] < 1.1


@pytest.mark.parametrize(("range_scale", "lateral_scale"), [(0.35, 0.8), (1.8, 1.2)])
def test_sensor_model_fits_the_true_scanner_from_the_preset(registry, tmp_path, range_scale: float,
                                                            lateral_scale: float) -> None:
    room = plant_room()
    new = trimesh.creation.box(extents=(0.5, 0.5, 0.5))  # not in the CAD: its points are changed
    new.apply_translation((0.5, -1.2, 0.25))
    base = PRESETS["tof_low_cost"]
    true = base.model_copy(update={"range_sigma": [c * range_scale for c in base.range_sigma],
                                   "lateral_sigma": [c * lateral_scale for c in base.lateral_sigma]})
    spec = ScannerSpec(fov_deg=70.0, aspect=1.3, points_per_m2=3000.0, max_range=9.0)
    scans = []
    for k, eye in enumerate(((2.8, -2.5, 1.6), (2.5, 2.6, 1.2))):
        shot = simulate_scan([*room, new], np.asarray(eye), np.array([-1.0, 0.0, 0.6]), spec,
                             np.random.default_rng(10 + k), profile=true)
        from gdt_pipeline import Dataset

        scans.append(Dataset(f"scan{k}", "as-is", shot.points, viewpoints=np.asarray(eye)[None]))
    reference = Composite(tuple(cad_item(f"E0_part{k}", mesh) for k, mesh in enumerate(room)))
    ctx = stage_ctx(registry, "sensor_model", {"profile": "tof_low_cost", "self_calibrate": True}, scans, reference,
                    tmp_path)
    survey = sensor_survey(ctx.params, ctx.slots)
    record = survey["self_calibration"]
    # one common scale (the default): along the normals the lateral terms weigh about 1 % here, so the fit finds
    # the range terms' scale and carries the lateral terms along
    assert record["fitted"] and record["points"] > 5000 and record["lateral_share"] < 0.05
    assert record["range_scale"] == pytest.approx(range_scale, rel=0.1) == record["lateral_scale"]
    assert 0.02 < record["outlier_share"] < 0.2  # the new box (and beams that pass an edge)
    assert abs(record["bias"]) < 0.01 and 0.9 < record["normalized_rms"] < 1.1
    # the stage uses the fitted profile and records the fit (cloud normals in both runs: with the twin's, which
    # facet a point's beam is taken to meet within 3 σ depends on the σ)
    ctx = stage_ctx(registry, "sensor_model", {"profile": "tof_low_cost", "self_calibrate": True,
                                               "incidence_normals": "cloud"}, scans, reference, tmp_path)
    ctx = type(ctx)(**{**ctx.__dict__, "survey": survey})
    out = registry.get("sensor_model").run(ctx)["recent"]
    plain = stage_ctx(registry, "sensor_model", {"profile": "tof_low_cost", "incidence_normals": "cloud"}, scans,
                      reference, tmp_path)
    prior_out = registry.get("sensor_model").run(plain)["recent"]
    ratio = np.trace(out[0].element_covariance(), axis1=1, axis2=2) / np.trace(
        prior_out[0].element_covariance(), axis1=1, axis2=2)
    assert np.allclose(ratio, record["range_scale"] ** 2, rtol=1e-9)
    assert ctx.notes["self_calibration"]["range_scale"] == record["range_scale"]
    assert scaled_profile("tof_low_cost", 1.0).range_sigma == base.range_sigma  # the preset itself is untouched


def test_without_meshes_in_the_twin_the_prior_stays_with_a_warning(registry, tmp_path) -> None:
    from gdt_pipeline import Dataset

    pts = np.random.default_rng(0).uniform(-1, 1, (2000, 3))
    scans = [Dataset("scan", "as-is", pts, viewpoints=np.array([[3.0, 0, 0]]))]
    ctx = stage_ctx(registry, "sensor_model", {"profile": "tof_low_cost", "self_calibrate": True}, scans,
                    Composite(), tmp_path)
    survey = sensor_survey(ctx.params, ctx.slots)
    assert survey["self_calibration"]["fitted"] is False
    assert "holds no mesh" in survey["self_calibration"]["why"]
    assert survey["profile"]["range_sigma"] == PRESETS["tof_low_cost"].range_sigma
    assert sensor_survey(registry.get("sensor_model").params(profile="tof_low_cost"), ctx.slots) == {}


def test_a_self_calibrated_run_is_the_same_whole_or_in_tiles(registry, tmp_path) -> None:
    import json

    import open3d as o3d

    from gdt_pipeline.runner import TilingOptions, run_workflow
    from twin_store import TwinStore

    room = plant_room()
    trimesh.util.concatenate(room).export(tmp_path / "room.obj")
    true = PRESETS["tof_low_cost"].model_copy(update={"range_sigma": [c * 0.4 for c in (0.002, 0.0, 0.008)],
                                                      "lateral_sigma": [c * 0.4 for c in (0.002, 0.003)]})
    eye = np.array([2.8, -2.5, 1.6])
    spec = ScannerSpec(fov_deg=70.0, aspect=1.3, points_per_m2=2000.0, max_range=9.0)
    shot = simulate_scan(room, eye, np.array([-1.0, 0.0, 0.6]), spec, np.random.default_rng(4), profile=true)
    o3d.io.write_point_cloud(str(tmp_path / "scan.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        shot.points)))
    (tmp_path / "scan_pose.json").write_text(json.dumps({"viewpoint": eye.tolist()}))
    (tmp_path / "wf.yaml").write_text(
        "name: selfcal\ntwin: twin\nseed: 3\nepochs:\n  - {id: E0, role: as-designed, inputs: [{path: room.obj}]}\n"
        "  - {id: E1, role: as-is, inputs: [{path: scan.ply, name: scan}]}\nstages:\n"
        "  - {uses: constant, role: as-designed, with: {model: box, half_widths: [0.0005, 0.0005, 0.0005]}}\n"
        "  - {uses: sensor_model, role: as-is, with: {profile: tof_low_cost, self_calibrate: true}}\n"
        "  - {uses: nearest, role: as-is}\n  - {uses: bhattacharyya, role: as-is}\n"
        "  - {uses: fixed, role: as-is, with: {tau: 10}}\n  - uses: keep_unchanged\n")
    whole = run_workflow(tmp_path / "wf.yaml", registry=registry).twin
    tiled = run_workflow(tmp_path / "wf.yaml", registry=registry, twin=tmp_path / "tiled",
                         tiling=TilingOptions(tile=1.5)).twin
    reports = [next(st["report"] for st in TwinStore.open(t).provenance("E1")["stages"]
                    if st["uses"] == "sensor_model") for t in (whole, tiled)]
    assert reports[0]["self_calibration"] == reports[1]["self_calibration"]
    assert reports[0]["self_calibration"]["range_scale"] == pytest.approx(0.4, rel=0.1)
    (a,), (b,) = (TwinStore.open(t).read_epoch("E1", ["E1_scan"]) for t in (whole, tiled))
    assert np.array_equal(a.covariance, b.covariance) and np.array_equal(a.state, b.state)
