"""The region of view by depth images (``sight: depth``): removal needs a station to have seen through an element's
place, noisy long-range scans keep present objects present, and facets are judged over their whole area."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import trimesh

from gdt_pipeline import Composite, Dataset, GaussianUncertainty
from gdt_pipeline.plugins import load_registry
from gdt_pipeline.region_of_view.samples import area_samples, sub_centroids
from gdt_pipeline.runner import read_pose_file
from gdt_pipeline.sensors import SensorProfile
from gdt_pipeline.simulation.scanner import ScannerSpec, simulate_scan
from tests.rov_helpers import cad_item, stage_ctx

EYE = np.zeros(3)
# the low-cost ToF of the pipe-rack report: along the beam (1 mm + 2.5 mm·r²)/cos θ, across it 1 mm + 0.8 mm·r
TOF = SensorProfile(name="tof_report", units="m", range_sigma=[0.001, 0.0, 0.0025], lateral_sigma=[0.001, 0.0008],
                    min_cos_incidence=0.2)


@pytest.fixture(scope="module")
def registry():
    return load_registry()


def _box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=extents)
    box.apply_translation(centre)
    return box


def _measured(meshes: list, profile: SensorProfile, seed: int, name: str = "scan", target=(3.5, 0, 0),
              density: float = 20000.0) -> Dataset:
    """A simulated pinhole scan of ``meshes`` from the origin with the profile's anisotropic covariance."""
    spec = ScannerSpec(fov_deg=30.0, aspect=1.0, points_per_m2=density, max_range=10.0)
    scan = simulate_scan(meshes, EYE, np.asarray(target, float), spec, np.random.default_rng(seed), profile=profile)
    d = scan.clean - EYE
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    dd = d[:, :, None] * d[:, None, :]
    cov = scan.sigma_range[:, None, None] ** 2 * dd + scan.sigma_lateral[:, None, None] ** 2 * (np.eye(3) - dd)
    return Dataset(name, "as-is", scan.points, viewpoints=EYE[None]).with_uncertainty(GaussianUncertainty(cov))


def _facing(mesh: trimesh.Trimesh) -> np.ndarray:
    """The facets the sensor at the origin sees at under 85° of incidence (beyond, no facet is judged)."""
    d = EYE - mesh.triangles_center
    return np.einsum("ij,ij->i", mesh.face_normals, d / np.linalg.norm(d, axis=1, keepdims=True)) > np.cos(
        np.radians(85.0))


def _area(mesh: trimesh.Trimesh, mask: np.ndarray) -> float:
    return float(mesh.area_faces[mask].sum() / mesh.area_faces.sum()) if mask.size else 0.0


def test_sub_triangles_cover_the_facet_in_equal_parts() -> None:
    for m in range(1, 9):
        bary = sub_centroids(m)
        assert len(bary) == m * m and np.allclose(bary.sum(axis=1), 1) and bary.min() > 0
        assert np.allclose(bary.mean(axis=0), 1 / 3)  # equal areas: the centroids average to the facet's centroid
    tri = trimesh.Trimesh(np.array([[0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 0.01], [0.01, 0, 0.01],
                                    [0, 0.01, 0.01]]), np.array([[0, 1, 2], [3, 4, 5]]), process=False)
    ds = Dataset("t", "as-designed", tri.vertices, faces=tri.faces)
    _, owner = area_samples(ds, spacing=0.01, cap=64)
    assert np.bincount(owner).tolist() == [64, 1]  # the large facet at the cap, the small one its centroid


def test_noisy_tof_scan_finds_the_removed_cabinet_and_keeps_the_present_one(registry, tmp_path) -> None:
    # the pipe-rack case: a plate 3.5 m away with a cabinet removed and one still there, σ along the beam ≈ 3 cm
    plate = _box((0.02, 1.8, 1.2), (3.51, 0, 0))
    removed = _box((0.3, 0.3, 0.3), (3.05, -0.55, 0.0))
    present = _box((0.3, 0.3, 0.3), (3.05, 0.55, 0.0))
    reference = Composite((cad_item("E0_plate", plate), cad_item("E0_removed", removed),
                           cad_item("E0_present", present)))
    scan = _measured([plate, present], TOF, seed=1)
    ctx = stage_ctx(registry, "manual_box", {"lower": [2, -1, -1], "upper": [4, 1, 1]}, [scan], reference, tmp_path)
    rov = registry.get("manual_box").run(ctx)["rov"]
    facing = {"E0_removed": _facing(removed), "E0_present": _facing(present)}
    assert facing["E0_removed"].sum() == 4  # the front and the side towards the sensor, at 81°
    gone = rov.views["E0_removed"].in_view & ~rov.views["E0_removed"].matched
    assert _area(removed, gone & facing["E0_removed"]) / _area(removed, facing["E0_removed"]) >= 0.95
    kept = rov.views["E0_present"].in_view & rov.views["E0_present"].matched
    assert _area(present, kept & facing["E0_present"]) / _area(present, facing["E0_present"]) >= 0.95
    assert not (rov.views["E0_present"].in_view & ~rov.views["E0_present"].matched).any()
    assert not (rov.views["E0_plate"].in_view & ~rov.views["E0_plate"].matched).any()  # the plate behind both is there


def test_a_large_facet_is_judged_on_its_area_not_its_middle(registry, tmp_path) -> None:
    # a 1 m square plate of two triangles at 3 m; the scan finds it only in a 30 cm square around each triangle's
    # centroid and sees a wall 0.5 m behind everywhere else: by the centroid both triangles are present
    plate = trimesh.Trimesh(np.array([[3.0, -0.5, -0.5], [3.0, 0.5, -0.5], [3.0, 0.5, 0.5], [3.0, -0.5, 0.5]]),
                            np.array([[0, 2, 1], [0, 3, 2]]), process=False)
    reference = Composite((cad_item("E0_plate", plate),))
    g = np.arange(-0.7, 0.7, 0.005)
    y, z = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    x = np.full(y.size, 3.5)
    for c in plate.triangles_center:
        near = (np.abs(y - c[1]) < 0.15) & (np.abs(z - c[2]) < 0.15)
        x[near] = 3.0
    pts = np.column_stack([x, y, z])
    scan = Dataset("scan", "as-is", pts, viewpoints=EYE[None]).with_uncertainty(
        GaussianUncertainty(np.broadcast_to(np.eye(3) * 1e-6, (len(pts), 3, 3))))
    ctx = stage_ctx(registry, "manual_box", {"lower": [2, -1, -1], "upper": [4, 1, 1]}, [scan], reference, tmp_path)
    rov = registry.get("manual_box").run(ctx)["rov"]
    plate = rov.views["E0_plate"]
    assert plate.in_view.all() and not plate.matched.any()  # removed: most of it is gone
    kept_share = 2 * 0.3 * 0.3 / 1.0  # the two found squares (each inside its triangle) of the plate's area
    assert np.allclose(rov.views["E0_plate"].removed_fraction, 1 - kept_share, atol=0.06)
    assert np.allclose(rov.views["E0_plate"].seen_fraction, 1.0)


def test_empty_space_counts_as_seen_through_only_within_a_pose_files_range(registry, tmp_path) -> None:
    # a cube removed from in front of nothing: a scanner whose pose file states its range saw empty space there; a
    # scan with only a viewpoint says nothing about where it found no surface
    cube = _box((0.2, 0.2, 0.2), (2.5, 0.4, 0.0))
    other = _box((0.2, 0.2, 0.2), (2.5, -0.4, 0.0))
    reference = Composite((cad_item("E0_cube", cube), cad_item("E0_other", other)))
    scan = _measured([other], TOF, seed=2, target=(2.5, 0, 0), density=40000.0)
    facing = _facing(cube)
    ctx = stage_ctx(registry, "sensor_frustum", {}, [scan], reference, tmp_path)
    rov = registry.get("sensor_frustum").run(ctx)["rov"]
    assert not rov.views["E0_cube"].in_view.any()  # no evidence either way: outside the region of view
    pose = {"viewpoint": [0, 0, 0], "target": [2.5, 0, 0], "scanner": {"kind": "pinhole", "fov_deg": 30.0,
                                                                       "aspect": 1.0, "max_range": 10.0}}
    pose_file = tmp_path / "scan_pose.json"
    pose_file.write_text(json.dumps(pose))
    scan = dataclasses.replace(scan, pose=read_pose_file(pose_file))  # as the engine gives it to every stage
    ctx = stage_ctx(registry, "sensor_frustum", {}, [scan], reference, tmp_path)
    rov = registry.get("sensor_frustum").run(ctx)["rov"]
    assert rov.views["E0_cube"].in_view[facing].all() and not rov.views["E0_cube"].matched[facing].any()
    assert rov.views["E0_other"].matched[rov.views["E0_other"].in_view].all()


def test_the_view_does_not_depend_on_the_order_of_the_points(registry, tmp_path) -> None:
    plate = _box((0.02, 1.4, 1.2), (3.51, 0, 0))
    removed = _box((0.3, 0.3, 0.3), (3.05, -0.3, 0.0))
    reference = Composite((cad_item("E0_plate", plate), cad_item("E0_removed", removed)))
    scan = _measured([plate], TOF, seed=3)
    perm = np.random.default_rng(0).permutation(scan.n_elements)
    shuffled = Dataset("scan", "as-is", scan.points[perm], viewpoints=EYE[None]).with_uncertainty(
        GaussianUncertainty(scan.element_covariance()[perm]))
    views = []
    for ds in (scan, shuffled):
        ctx = stage_ctx(registry, "manual_box", {"lower": [2, -1, -1], "upper": [4, 1, 1]}, [ds], reference, tmp_path)
        rov = registry.get("manual_box").run(ctx)["rov"]
        removed = rov.views["E0_removed"]
        views.append((removed.in_view, removed.matched, removed.removed_fraction))
    for a, b in zip(*views, strict=True):
        assert np.array_equal(a, b)


def test_point_spacing_over_chunks_equals_one_tree(monkeypatch):
    """The spacing over several arrays, a chunk's tree at a time, is the one tree's over their rows stacked, to the
    bit: duplicates, chunk edges and rows whose nearest neighbour lies in another array included."""
    import importlib

    from scipy.spatial import cKDTree

    look = importlib.import_module("gdt_pipeline.region_of_view.look")  # the package's ``look`` is the function

    rng = np.random.default_rng(5)
    parts = [rng.uniform(0, 1, (n, 3)) for n in (3_001, 1, 4_500, 2)]
    parts[2][10] = parts[0][0]  # a duplicate across arrays: spacing 0 for that row
    stacked = np.vstack(parts)
    step = max(1, len(stacked) // 500)
    d, _ = cKDTree(stacked).query(stacked[::step], k=2)
    monkeypatch.setattr(look, "SPACING_SAMPLE", 500)
    monkeypatch.setattr(look, "SPACING_CHUNK", 1_000)
    rows = np.arange(0, len(stacked), step)
    np.testing.assert_array_equal(look._nearest_other(parts, rows), d[:, 1])
    assert look.point_spacing(parts) == float(np.median(d[:, 1]))
    assert look.point_spacing(stacked) == float(np.median(d[:, 1]))
    assert look.point_spacing([np.zeros((1, 3))]) == 0.0
