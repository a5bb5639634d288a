"""Neighbourhood expectation (``auto``'s ``expectation: neighbourhood``): on a noisy scan of a plane the pooled
offsets shrink as √n and their stated σ matches their spread; a patch raised by one σ, which no single point
shows, stands out while the plane around it stays quiet; a step of five σ smears no further than a few cm; a
sparse cloud keeps the per-point test; whole and tiled runs agree (a tile pools its core bit for bit as the whole
epoch does) and the twin keeps every input point."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from gdt_pipeline import Dataset, GaussianUncertainty
from stages.correspondence.expectation import PoolingParams, pooled_expectations

SIGMA = 0.03  # m along the beam
LATERAL = 0.002


class _Meshes:
    """An Open3D scene of one mesh, as the correspondence stage's ReferenceMeshes holds it."""

    def __init__(self, mesh: trimesh.Trimesh) -> None:
        import open3d as o3d

        self.origin = np.zeros(3)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                                 o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
        self.normals = [np.asarray(mesh.face_normals)]


def _scan(rng: np.random.Generator, spacing: float, raise_by: float = 0.0) -> tuple[Dataset, np.ndarray, np.ndarray]:
    """Points on the plane z = 0 over 2 m × 2 m seen from 2 m above, beam noise SIGMA; those with |x|, |y| < 0.4
    raised by ``raise_by``. Returns the dataset, the station and the raised mask."""
    g = np.arange(-1.0, 1.0, spacing)
    xy = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    raised = (np.abs(xy) < 0.4).all(axis=1)
    clean = np.column_stack([xy, np.where(raised, raise_by, 0.0)])
    station = np.array([0.3, -0.2, 2.0])
    beam = clean - station
    beam /= np.linalg.norm(beam, axis=1, keepdims=True)
    across = np.eye(3)[None] - np.einsum("ni,nj->nij", beam, beam)
    cov = SIGMA**2 * np.einsum("ni,nj->nij", beam, beam) + LATERAL**2 * across
    noisy = clean + beam * rng.normal(0, SIGMA, (len(clean), 1)) + np.einsum(
        "nij,nj->ni", across, rng.normal(0, LATERAL, (len(clean), 3)))
    return Dataset("scan", "as-is", noisy, uncertainty=GaussianUncertainty(cov)), station, raised


def _plane() -> _Meshes:
    return _Meshes(trimesh.creation.box(extents=(3.0, 3.0, 0.02)).apply_translation((0, 0, -0.01)))


def _pool(ds: Dataset, station: np.ndarray | None, meshes: _Meshes, neighbours: int = 256):
    (found,), _ = pooled_expectations([ds], [station], meshes.scene, meshes.origin, meshes.normals,
                                      PoolingParams(neighbours, 0.1, 1.5, 4.0))
    return found


def test_pooled_offsets_shrink_with_the_neighbours_and_state_their_spread() -> None:
    ds, station, _ = _scan(np.random.default_rng(1), 0.01)
    found = _pool(ds, station, _plane())
    interior = (np.abs(ds.points[:, :2]) < 0.8).all(axis=1)
    z_expected = found.position[interior, 2]
    sd = np.sqrt(found.covariance[interior, 2, 2])
    pooled = np.median(found.pooled[interior])
    assert pooled >= 129  # the point and at least two full quadrants of 64
    # n independent points: σ/√n stated, and the spread of the estimates themselves matches it within 15 %
    sigma_normal = np.sqrt(np.median(np.einsum("i,nij,j->n", [0, 0, 1.0], ds.uncertainty.cov, [0, 0, 1.0])))
    assert np.median(sd) == pytest.approx(sigma_normal / np.sqrt(pooled), rel=0.15)
    z = z_expected / sd
    assert np.std(z) == pytest.approx(1.0, abs=0.1)
    assert abs(np.mean(z)) < 0.25  # no bias from range-dependent weights (inverse-variance ones gave 0.9)
    assert np.mean(np.abs(z) > 3) < 0.006  # 0.27 % for a normal
    # the input points are untouched; only the expectation moved
    assert np.std(ds.points[interior, 2]) > 6 * np.std(z_expected)


def _edge_distance(points: np.ndarray, raised: np.ndarray) -> np.ndarray:
    """Distance in x, y to the raised square's edge."""
    outside = np.linalg.norm(np.maximum(np.abs(points[:, :2]) - 0.4, 0), axis=1)
    return np.where(raised, np.min(0.4 - np.abs(points[:, :2]), axis=1), outside)


def test_a_patch_raised_by_one_sigma_stands_out_and_the_plane_around_stays_quiet() -> None:
    ds, station, raised = _scan(np.random.default_rng(2), 0.01, raise_by=SIGMA)
    found = _pool(ds, station, _plane())
    z = found.position[:, 2] / np.sqrt(found.covariance[:, 2, 2])
    own = ds.points[:, 2] / SIGMA
    edge = _edge_distance(ds.points, raised)
    inner = raised & (edge > 0.05)
    plane = ~raised & (edge > 0.08) & (np.abs(ds.points[:, :2]) < 0.9).all(axis=1)
    assert np.mean(own[inner] > 2.58) < 0.25  # one σ: a point alone rarely shows it
    assert np.mean(z[inner] > 2.58) > 0.95  # its neighbourhood does
    assert np.mean(np.abs(z[plane]) > 2.58) < 0.03  # and the plane 8 cm and more from it stays quiet


def test_a_step_of_five_sigma_does_not_smear_past_a_few_centimetres() -> None:
    ds, station, raised = _scan(np.random.default_rng(6), 0.01, raise_by=5 * SIGMA)
    found = _pool(ds, station, _plane())
    z = found.position[:, 2] / np.sqrt(found.covariance[:, 2, 2])
    edge = _edge_distance(ds.points, raised)
    assert np.mean(z[raised & (edge < 0.02)] > 2.58) > 0.95
    assert np.mean(z[~raised & (edge > 0.04) & (edge < 0.08)] > 2.58) < 0.1


def test_a_sparse_cloud_keeps_the_per_point_test() -> None:
    ds, station, _ = _scan(np.random.default_rng(3), 0.12)  # 12 cm apart: fewer than 8 within the 10 cm radius
    found = _pool(ds, station, _plane())
    assert np.all(found.pooled == 1)
    assert np.array_equal(found.position, ds.points)
    assert np.array_equal(found.covariance, np.asarray(ds.uncertainty.cov))


def test_without_a_station_isotropic_points_anchor_on_the_closest_point() -> None:
    rng = np.random.default_rng(4)
    g = np.arange(-0.5, 0.5, 0.01)
    pts = np.column_stack([np.stack(np.meshgrid(g, g), -1).reshape(-1, 2), np.zeros(len(g) ** 2)])
    pts += rng.normal(0, 0.01, pts.shape)
    ds = Dataset("iso", "as-is", pts, uncertainty=GaussianUncertainty.isotropic(0.01))
    # a slab thicker than the noise: without a station a point nearer a thin wall's far face is anchored there
    found = _pool(ds, None, _Meshes(trimesh.creation.box(extents=(3.0, 3.0, 0.2)).apply_translation((0, 0, -0.1))))
    inner = (np.abs(pts[:, :2]) < 0.3).all(axis=1)
    assert np.median(found.pooled[inner]) >= 129
    assert np.std(found.position[inner, 2]) < 0.2 * 0.01


def _pooled_workflow(tmp_path, expectation: str, twin: str) -> object:
    """The room CAD and one ToF scan (preset noise, about 15 cm along the beam at 3.8 m) of the room with a new
    slab 12 cm tall (0.8 σ) on the floor; the chain with ``auto``'s ``expectation``."""
    (tmp_path / f"{twin}.yaml").write_text(
        f"name: pooled\ntwin: {twin}\nseed: 3\nepochs:\n"
        "  - {id: E0, role: as-designed, inputs: [{path: room.obj}]}\n"
        "  - {id: E1, role: as-is, inputs: [{path: scan.ply, name: scan}]}\nstages:\n"
        "  - {uses: constant, role: as-designed, with: {model: box, half_widths: [0.0005, 0.0005, 0.0005]}}\n"
        "  - {uses: sensor_model, role: as-is, with: {profile: tof_low_cost}}\n"
        f"  - {{uses: auto, role: as-is, with: {{expectation: {expectation}}}}}\n"
        "  - {uses: bhattacharyya, role: as-is}\n"
        "  - {uses: calibrated_threshold, role: as-is, with: {false_alarm: 0.01}}\n  - uses: keep_unchanged\n")
    return tmp_path / f"{twin}.yaml"


def test_a_slab_under_the_noise_is_found_pooled_the_same_whole_or_in_tiles(registry, tmp_path) -> None:
    import open3d as o3d

    from gdt_pipeline.runner import TilingOptions, run_workflow
    from gdt_pipeline.sensors import PRESETS
    from gdt_pipeline.simulation.scanner import ScannerSpec, simulate_scan
    from gdt_pipeline.types import ChangeState
    from tests.rov_helpers import plant_room
    from twin_store import TwinStore

    room = plant_room()
    trimesh.util.concatenate(room).export(tmp_path / "room.obj")
    slab = trimesh.creation.box(extents=(0.4, 0.4, 0.12)).apply_translation((0.6, -1.0, 0.06))
    eye = np.array([2.8, -2.5, 1.6])
    spec = ScannerSpec(fov_deg=70.0, aspect=1.3, points_per_m2=1500.0, max_range=9.0)
    shot = simulate_scan([*room, slab], eye, np.array([-1.0, 0.0, 0.6]), spec, np.random.default_rng(5),
                         profile=PRESETS["tof_low_cost"])
    o3d.io.write_point_cloud(str(tmp_path / "scan.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        shot.points)))
    (tmp_path / "scan_pose.json").write_text(json.dumps({"viewpoint": eye.tolist()}))
    twins = {name: run_workflow(_pooled_workflow(tmp_path, exp, name), registry=registry).twin
             for name, exp in (("per_point", "point"), ("pooled", "neighbourhood"))}
    tiled = run_workflow(_pooled_workflow(tmp_path, "neighbourhood", "tiled"), registry=registry,
                         tiling=TilingOptions(tile=3.0)).twin
    sets = {name: TwinStore.open(t).read_epoch("E1", ["E1_scan"])[0] for name, t in {**twins, "tiled": tiled}.items()}
    a, b = sets["pooled"], sets["tiled"]
    assert np.array_equal(a.state, b.state) and np.allclose(a.score, b.score, equal_nan=True)
    # the twin keeps every input point with its own covariance; only the test used the expectation
    assert len(a.points) == len(shot.points) and np.allclose(a.points, shot.points, atol=1e-6)
    assert np.array_equal(a.covariance, sets["per_point"].covariance)
    on_slab = shot.object_id == len(room)
    found = {name: (s.state == ChangeState.NEW)[on_slab].mean() for name, s in sets.items()}
    assert found["per_point"] < 0.15 and found["pooled"] > 0.7
    assert (a.state == ChangeState.NEW)[~on_slab].mean() < 0.03
    report = next(st["report"] for st in TwinStore.open(twins["pooled"]).provenance("E1")["stages"]
                  if st["uses"] == "auto")
    assert report["expectation"]["pooled_share"] > 0.9


def _scan_from(rng: np.random.Generator, station: np.ndarray, raise_by: float) -> Dataset:
    """``_scan``'s points seen from ``station``, 2 cm apart."""
    g = np.arange(-1.0, 1.0, 0.02)
    xy = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    clean = np.column_stack([xy, np.where((np.abs(xy) < 0.4).all(axis=1), raise_by, 0.0)])
    beam = clean - station
    beam /= np.linalg.norm(beam, axis=1, keepdims=True)
    cov = SIGMA**2 * np.einsum("ni,nj->nij", beam, beam) + LATERAL**2 * (np.eye(3)[None] - np.einsum(
        "ni,nj->nij", beam, beam))
    noisy = clean + beam * rng.normal(0, SIGMA, (len(clean), 1)) + rng.normal(0, LATERAL, clean.shape)
    return Dataset(f"scan{station[0]:+.1f}", "as-is", noisy, uncertainty=GaussianUncertainty(cov))


def test_a_tile_pools_its_core_as_the_whole_epoch_does_and_leaves_the_rest_its_own() -> None:
    # a slab one σ tall on the plane: beams over it cross two surfaces within their noise, so the second pass's
    # anchors depend on the first pass of neighbours a tile must pool too
    rng = np.random.default_rng(8)
    stations = [np.array([0.9, -0.4, 1.6]), np.array([-1.1, 0.5, 1.4])]
    scans = [_scan_from(rng, st, SIGMA) for st in stations]
    slab = trimesh.creation.box(extents=(0.8, 0.8, SIGMA)).apply_translation((0, 0, SIGMA / 2))
    meshes = _Meshes(trimesh.util.concatenate([trimesh.creation.box(extents=(3.0, 3.0, 0.02)).apply_translation(
        (0, 0, -0.01)), slab]))
    params = PoolingParams(64, 0.1, 1.5, 4.0)
    whole, reaches = pooled_expectations(scans, stations, meshes.scene, meshes.origin, meshes.normals, params)
    core = [(np.abs(ds.points[:, 0] - 0.35) < 0.15) for ds in scans]  # across the slab's edge
    halo = max(float(r[c].max()) for r, c in zip(reaches, core, strict=True))
    crop = [np.abs(ds.points[:, 0] - 0.35) < 0.15 + halo for ds in scans]
    assert 0 < sum(int(c.sum()) for c in crop) < sum(ds.n_elements for ds in scans)
    cropped = [Dataset(ds.name, ds.role, ds.points[c], uncertainty=GaussianUncertainty(
        np.asarray(ds.uncertainty.cov)[c])) for ds, c in zip(scans, crop, strict=True)]
    kept = [k[c] for k, c in zip(core, crop, strict=True)]
    tiled, _ = pooled_expectations(cropped, stations, meshes.scene, meshes.origin, meshes.normals, params, kept)
    for w, t, ds, c, k, inner in zip(whole, tiled, cropped, crop, kept, core, strict=True):
        assert np.median(w.pooled[inner]) > 30
        assert np.array_equal(t.position[k], w.position[c][k]) and np.array_equal(t.covariance[k], w.covariance[c][k])
        assert np.array_equal(t.pooled[k], w.pooled[c][k])
        assert np.array_equal(t.position[~k], ds.points[~k]) and np.all(t.pooled[~k] == 1)
