"""Registrars: a known rigid transform is recovered on the test scene to < 1 mm and < 0.05°; stable_areas beats a
plain ICP when 10 % of the points lie on a new object; coarse alignment from far off; given/identity; the transform
covariance; and the real TTP datum offset."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from gdt_pipeline import Composite, CompositeItem, Dataset, EpochInfo, StageContext
from gdt_pipeline.simulation import scene_objects, simulate_stations

from .conftest import SHARED_DATA

T_TRUE = np.eye(4)
T_TRUE[:3, :3] = Rotation.from_euler("xyz", [1.5, -2.0, 3.0], degrees=True).as_matrix()
T_TRUE[:3, 3] = [0.05, -0.03, 0.02]


def cad_composite() -> tuple[Composite, list[trimesh.Trimesh]]:
    cad = [m for m, in_cad in scene_objects().values() if in_cad]
    items = tuple(CompositeItem(f"E0_{i}", Dataset(f"c{i}", "as-designed", m.vertices, faces=m.faces), "E0",
                                np.zeros(len(m.faces)), np.full(len(m.faces), np.nan), np.zeros(len(m.faces)),
                                np.ones(len(m.faces), bool)) for i, m in enumerate(cad))
    return Composite(items), cad


def scan_of(meshes: list, noise: float, seed: int = 0) -> np.ndarray:
    az = np.radians([-60.0, 30.0, 150.0])
    vps = np.column_stack([2.0 * np.cos(az), 2.0 * np.sin(az), np.full(3, 1.2)])
    return simulate_stations(meshes, vps, np.array([0, 0, 0.15]), rng=np.random.default_rng(seed),
                            points_per_m2=20000, noise_sigma=noise)


def _register(registry, name: str, params: dict, points: np.ndarray, comp: Composite, tmp_path: Path = Path(".")):
    spec = registry.get(name)
    ctx = StageContext(stage=spec, params=spec.params.model_validate(params),
                       slots={"recent": [Dataset("scan", "as-is", points)], "reference": comp},
                       epoch=EpochInfo("E1", 1, "as-is", 3, tmp_path, "m"), rng=np.random.default_rng(3), seed=3,
                       log=logging.getLogger("test"))
    return spec.run(ctx), ctx


def transform_errors(t_est: np.ndarray, t_true: np.ndarray, pts: np.ndarray) -> tuple[float, float]:
    """Rotation error (degrees) and the largest point displacement error over ``pts``."""
    e = t_est @ t_true
    angle = np.degrees(np.arccos(np.clip((np.trace(e[:3, :3]) - 1) / 2, -1, 1)))
    return angle, float(np.max(np.linalg.norm(pts @ e[:3, :3].T + e[:3, 3] - pts, axis=1)))


@pytest.mark.parametrize("name", ["gicp", "point_to_plane"])
def test_known_transform_is_recovered(registry, name: str) -> None:
    comp, cad = cad_composite()
    scan = scan_of(cad, noise=0.004)  # the noisy ToF-class scan of the demo
    truth = scan["points"]
    moved = truth @ T_TRUE[:3, :3].T + T_TRUE[:3, 3]
    out, ctx = _register(registry, name, {}, moved, comp)
    reg = out["registration"]
    angle, shift = transform_errors(reg.transform, T_TRUE, truth)
    assert angle < 0.05 and shift < 0.001, (angle, shift)
    np.testing.assert_allclose(out["recent"][0].points, truth, atol=0.001)
    cov = reg.covariance
    assert cov.shape == (6, 6) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.all(np.sqrt(np.diag(cov)[3:]) < 0.001)  # sub-millimetre translation sigma on ~15 k points
    assert ctx.notes["fitness"] > 0.9 and ctx.notes["rotation_deg"] == pytest.approx(np.degrees(
        np.arccos((np.trace(T_TRUE[:3, :3]) - 1) / 2)), abs=0.05)


def test_stable_areas_beat_plain_icp_with_a_new_object(registry) -> None:
    comp, cad = cad_composite()
    scan = scan_of(cad, noise=0.002)["points"]
    # a new panel 2 cm in front of the small cuboid's +x face: within the finest correspondence distance of the
    # schedule scaled to the scan (2 x 4.9 mm spacing x 2.5 = 2.5 cm), so it biases a plain ICP
    rng = np.random.default_rng(5)
    small = cad[0]
    x_face = small.bounds[1][0]
    n_new = len(scan) // 9  # 10 % of all points
    panel = np.column_stack([np.full(n_new, x_face + 0.02), rng.uniform(small.bounds[0][1], small.bounds[1][1], n_new),
                             rng.uniform(0.0, 0.15, n_new)]) + rng.normal(0, 0.002, (n_new, 3))
    pts = np.vstack([scan, panel])
    moved = pts @ T_TRUE[:3, :3].T + T_TRUE[:3, 3]
    plain, _ = _register(registry, "gicp", {}, moved, comp)
    stable, ctx = _register(registry, "stable_areas", {}, moved, comp)
    _, err_plain = transform_errors(plain["registration"].transform, T_TRUE, scan)
    _, err_stable = transform_errors(stable["registration"].transform, T_TRUE, scan)
    assert err_stable < err_plain / 5 and err_plain > 0.001, (err_stable, err_plain)
    assert err_stable < 0.001
    assert ctx.notes["stable_points"] < ctx.notes["all_points"] - 0.8 * n_new  # the panel was trimmed away


def test_coarse_alignment_from_far_off(registry) -> None:
    comp, cad = cad_composite()
    truth = scan_of(cad, noise=0.001)["points"]
    far = np.eye(4)
    far[:3, :3] = Rotation.from_euler("z", 120, degrees=True).as_matrix()
    far[:3, 3] = [0.5, -0.3, 0.05]
    moved = truth @ far[:3, :3].T + far[:3, 3]
    plain, _ = _register(registry, "gicp", {}, moved, comp)
    out, ctx = _register(registry, "coarse", {}, moved, comp)  # features at the schedule's coarsest voxel
    angle, shift = transform_errors(out["registration"].transform, far, truth)
    assert angle < 0.05 and shift < 0.001, (angle, shift, ctx.notes)
    assert transform_errors(plain["registration"].transform, far, truth)[1] > 0.05  # ICP alone does not get there


def test_given_and_identity(registry, tmp_path: Path) -> None:
    comp, _ = cad_composite()
    pts = np.random.default_rng(0).normal(size=(10, 3))
    np.savetxt(tmp_path / "t.txt", T_TRUE)
    (tmp_path / "t.json").write_text(json.dumps(T_TRUE.tolist()))
    for params in ({"file": "t.txt"}, {"file": "t.json"}, {"transform": T_TRUE.tolist()}):
        out, _ = _register(registry, "given", params, pts, comp, tmp_path)
        np.testing.assert_allclose(out["recent"][0].points, pts @ T_TRUE[:3, :3].T + T_TRUE[:3, 3], atol=1e-12)
    scaled = np.eye(4)
    scaled[:3, :3] *= 2
    with pytest.raises(Exception, match="not a rotation"):
        registry.get("given").params.model_validate({"transform": scaled.tolist()})
    out, _ = _register(registry, "identity", {}, pts, comp)
    assert np.array_equal(out["recent"][0].points, pts)


def test_registration_in_a_workflow_with_propagation(cube_scene, registry) -> None:
    from gdt_pipeline.runner import run_workflow
    from twin_store import TwinStore

    from .conftest import write_cube_workflow, write_points_ply

    scan = np.loadtxt(cube_scene.scan, skiprows=7)
    write_points_ply(cube_scene.scan, scan @ T_TRUE[:3, :3].T + T_TRUE[:3, 3])
    wf = write_cube_workflow(cube_scene)
    wf.write_text(wf.read_text().replace("  - uses: identity\n    role: as-is\n",
                                         "  - uses: stable_areas\n    role: as-is\n    with: {voxels: [0.05, 0.02]}\n")
                  .replace("    with: {model: isotropic, sigma: 0.002}\n",
                           "    with: {model: isotropic, sigma: 0.002}\n  - uses: registration_propagation\n"
                           "    role: as-is\n"))
    twin = run_workflow(wf, registry=registry).twin
    prov = TwinStore.open(twin).provenance("E1")
    reg = prov["registration"]
    assert reg["method"] == "stable_areas+gicp" and len(reg["covariance"]) == 6
    angle, shift = transform_errors(np.asarray(reg["transform"]), T_TRUE, scan)
    assert angle < 0.05 and shift < 0.001
    rec = next(s for s in prov["stages"] if s["uses"] == "stable_areas")
    assert rec["report"]["fitness"] > 0.5
    scan_set = next(e for e in TwinStore.open(twin).read_epoch("E1") if e.key == "E1_scan")
    assert np.all(scan_set.covariance[:, 0] > 0.002**2)  # the registration's uncertainty was added
    state = scan_set.state
    tp = np.sum((state == 1) & cube_scene.changed)
    assert 2 * tp / (np.sum(state == 1) + cube_scene.changed.sum()) > 0.95


@pytest.mark.skipif(not (SHARED_DATA / "ttp_toronto_als").is_dir(), reason="../shared/data/ttp_toronto_als absent")
def test_real_als_datum_offset_is_found(registry) -> None:
    """TTP 2023 ground sits about 0.41 m below 2015 (data README); a registrar must find it."""
    import laspy
    from scipy.spatial import cKDTree

    def ground(name: str) -> np.ndarray:
        las = laspy.read(str(SHARED_DATA / "ttp_toronto_als" / name))
        return np.column_stack([las.x, las.y, las.z])[np.asarray(las.classification) == 2]

    g15, g23 = ground("TTP_2015.laz"), ground("TTP_2023.laz")
    n = len(g15)
    comp = Composite((CompositeItem("E0_g15", Dataset("g15", "as-is", g15), "E0", np.zeros(n), np.full(n, np.nan),
                                    np.zeros(n), np.ones(n, bool)),))
    tree = cKDTree(g15[:, :2])

    def median_dz(pts: np.ndarray) -> float:
        d, j = tree.query(pts[:, :2], distance_upper_bound=3.0)
        ok = np.isfinite(d)
        return float(np.median(pts[ok, 2] - g15[j[ok], 2]))

    assert median_dz(g23) == pytest.approx(-0.41, abs=0.03)
    out, ctx = _register(registry, "stable_areas", {"voxels": [8.0, 4.0], "max_distance_factor": 2.0,
                                                    "method": "point_to_plane"}, g23, comp)
    assert abs(median_dz(out["recent"][0].points)) < 0.03
    assert ctx.notes["shift_at_center"][2] == pytest.approx(0.41, abs=0.05)
