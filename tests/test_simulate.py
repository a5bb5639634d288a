"""The scanner simulator and the paper's scenes: noise as modelled, real occlusion, truth that matches geometry."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import trimesh

from gdt_pipeline.evaluation import prf, sweep, threshold_candidates
from gdt_pipeline.sensors import PRESETS
from gdt_pipeline.simulation import ScannerSpec, make_fuselage_scene, simulate_scan, write_scan
from gdt_pipeline.simulation.fuselage import NEW_BRACKETS, fuselage_objects


def _wall(x: float = 0.0, size: float = 4.0) -> trimesh.Trimesh:
    """A square wall in the plane x = const, facing -x."""
    box = trimesh.creation.box(extents=(0.01, size, size))
    box.apply_translation((x + 0.005, 0.0, 0.0))
    return box


def _beam_frame(scan):
    d = scan.clean - scan.viewpoint
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d


@pytest.mark.parametrize("profile", ["tof_low_cost", "structured_light"])
def test_noise_along_and_across_the_beam_follows_the_profile_per_range_bin(profile: str) -> None:
    wall = _wall()
    wall.apply_transform(trimesh.transformations.rotation_matrix(np.radians(50), [0, 0, 1]))  # oblique: ranges vary
    spec = ScannerSpec(profile=profile, points_per_m2=40000, fov_deg=70, max_range=20)
    eye = np.array([-2.0, 0.0, 0.0])
    scan = simulate_scan([wall], eye, np.zeros(3), spec, np.random.default_rng(1))
    d = _beam_frame(scan)
    err = scan.points - scan.clean
    along = np.einsum("ij,ij->i", err, d)
    across = np.linalg.norm(err - along[:, None] * d, axis=1)
    rng = np.linalg.norm(scan.clean - eye, axis=1)
    # the truth's sigmas are the profile's formula at the true range and incidence
    normal = wall.face_normals[0]
    s_r, s_l = PRESETS[profile].sigmas(rng, np.abs(d @ normal), "m")
    np.testing.assert_allclose(scan.sigma_range, s_r, rtol=1e-6)
    np.testing.assert_allclose(scan.sigma_lateral, s_l, rtol=1e-6)
    assert len(scan.points) > 20000
    bins = np.quantile(rng, np.linspace(0, 1, 6))
    for lo, hi in itertools.pairwise(bins):
        sel = (rng >= lo) & (rng < hi)
        # std of the range error against the rms of the modelled sigma, within sampling error (~2 % at n > 4000)
        assert np.std(along[sel]) == pytest.approx(np.sqrt(np.mean(s_r[sel] ** 2)), rel=0.06)
        # the lateral error is 2-D: E|e|² = 2σ²
        assert np.sqrt(np.mean(across[sel] ** 2) / 2) == pytest.approx(np.sqrt(np.mean(s_l[sel] ** 2)), rel=0.06)
    if profile == "tof_low_cost":  # range noise grows with range (and incidence) for the ToF camera
        near, far = rng < np.quantile(rng, 0.2), rng > np.quantile(rng, 0.8)
        assert np.std(along[far]) > 1.3 * np.std(along[near])


def test_occluded_surface_gets_no_points_and_the_truth_names_what_was_hit() -> None:
    wall = _wall(x=2.0)
    blocker = trimesh.creation.box(extents=(0.2, 0.6, 0.6))
    blocker.apply_translation((1.0, 0.0, 0.0))
    eye = np.array([0.0, 0.0, 0.0])
    spec = ScannerSpec(profile="structured_light", points_per_m2=20000, fov_deg=60)
    scan = simulate_scan([wall, blocker], eye, np.array([2.0, 0, 0]), spec, np.random.default_rng(0))
    on_wall = scan.object_id == 0
    assert on_wall.any() and (~on_wall).any()
    # the blocker's shadow on the wall: |y|, |z| < 0.3 * 2.0 / 0.9 (seen from the eye past the blocker's front)
    shadow = (np.abs(scan.clean[:, 1]) < 0.3 * 2.0 / 1.1 - 0.01) & (np.abs(scan.clean[:, 2]) < 0.3 * 2.0 / 1.1 - 0.01)
    assert not np.any(on_wall & shadow)
    np.testing.assert_allclose(scan.clean[on_wall, 0], 2.0, atol=1e-5)
    np.testing.assert_allclose(scan.clean[~on_wall, 0], 0.9, atol=1e-5)


def test_registration_error_moves_the_whole_scan_rigidly_and_is_recorded(tmp_path) -> None:
    wall = _wall(x=2.0)
    spec = ScannerSpec(profile="structured_light", points_per_m2=5000, registration_sigma_deg=0.5,
                       registration_sigma_m=0.01)
    eye, aim = np.zeros(3), np.array([2.0, 0, 0])
    a = simulate_scan([wall], eye, aim, spec, np.random.default_rng(3))
    b = simulate_scan([wall], eye, aim, spec, np.random.default_rng(3))
    np.testing.assert_array_equal(a.points, b.points)  # seeded: the same scan
    err = a.registration_error
    assert not np.allclose(err, np.eye(4))
    np.testing.assert_allclose(err[:3, :3] @ err[:3, :3].T, np.eye(3), atol=1e-12)
    undone = (a.points - err[:3, 3]) @ err[:3, :3]
    assert np.abs(undone - a.clean).max() < 0.002  # only the sub-mm sensor noise is left
    files = write_scan(a, tmp_path / "s.ply", object_names=["wall"], spec=spec)
    pose = json.loads(files["pose"].read_text())
    np.testing.assert_allclose(pose["registration_error"], err)
    assert pose["scanner"]["profile"] == "structured_light"
    truth = np.load(files["truth"])
    np.testing.assert_array_equal(truth["clean"], a.clean)
    back = trimesh.load(files["scan"])
    np.testing.assert_allclose(np.asarray(back.vertices), a.points, atol=1e-9)
    mesh = write_scan(a, tmp_path / "m.ply", object_names=["wall"], spec=spec, as_mesh=True)
    surface = trimesh.load(mesh["scan"], force="mesh")
    assert len(surface.faces) > 100
    # the reconstructed surface lies on the (displaced) wall
    assert np.median(np.abs(((np.asarray(surface.vertices) - err[:3, 3]) @ err[:3, :3])[:, 0] - 2.0)) < 0.003


def test_fuselage_scene_truth_marks_exactly_the_new_brackets(tmp_path) -> None:
    objects = fuselage_objects()
    assert all(m.is_watertight for m, _ in objects.values())
    make_fuselage_scene(tmp_path, seed=0, points_per_m2=8000)
    scene = json.loads((tmp_path / "scene.json").read_text())
    states = scene["epochs"]["E1"]["objects"]
    assert sorted(n for n, s in states.items() if s == "new") == sorted(NEW_BRACKETS)
    assert [n for n, s in states.items() if s == "removed"] == ["bracket_removed"]
    changed, on_new = [], []
    for k in range(6):
        t = np.load(tmp_path / f"scan_E1_s{k}_truth.npz")
        names = np.array([str(n) for n in t["object_names"]])[t["object_id"]]
        changed.append(t["changed"])
        on_new.append(np.isin(names, list(NEW_BRACKETS)))
        assert "bracket_removed" not in set(names)
    changed, on_new = np.concatenate(changed), np.concatenate(on_new)
    assert not np.any(changed & ~on_new)  # nothing but a new bracket is off the CAD
    assert changed[on_new].mean() > 0.9  # and a new bracket is off the CAD except where it touches a frame web
    e1 = np.load(tmp_path / "truth_E1.npz")
    assert e1["removed__bracket_removed"].all() and not e1["removed__skin"].any()
    assert 0 < e1["in_view__bracket_removed"].sum() < len(e1["in_view__bracket_removed"])  # its front seen, back not


def test_precision_recall_and_sweeps_on_hand_made_cases() -> None:
    truth = np.array([1, 1, 1, 0, 0, 0, 0, 0], bool)
    pred = np.array([1, 1, 0, 1, 0, 0, 0, 0], bool)
    m = prf(pred, truth)
    assert (m["tp"], m["fp"], m["fn"]) == (2, 1, 1)
    assert m["precision"] == pytest.approx(2 / 3) and m["recall"] == pytest.approx(2 / 3)
    assert m["f1"] == pytest.approx(2 / 3) and m["false_alarm_rate"] == pytest.approx(1 / 5)
    none = prf(np.zeros(4, bool), np.zeros(4, bool))  # no change, nothing flagged: F1 undefined, no false alarms
    assert none["f1"] is None and none["precision"] is None and none["false_alarm_rate"] == 0.0
    d = np.array([0.5, 0.4, 0.3, 0.02, 0.01, 0.005, np.inf])
    t = np.array([1, 1, 1, 0, 0, 0, 1], bool)
    tau, best = sweep(d, t, threshold_candidates(d))
    assert 0.02 <= tau < 0.3 and best["f1"] == 1.0
