"""Uncertainty estimators: voxel MLE recovers known Gaussians, calibration recovers a simulated scanner's σ within
10 %, sensor-model covariances align with the beam, registration propagation matches Monte Carlo."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from gdt_pipeline import Dataset, EpochInfo, GaussianUncertainty, Registration, StageContext
from gdt_pipeline.sensors import PRESETS, calibrate, load_profile
from stages.uncertainty.estimators import propagate_registration, voxel_mle

from .conftest import SHARED_DATA, run_gdt, write_points_ply


def _run(registry, name: str, params: dict, recent: list[Dataset], tmp_path: Path, **slots) -> list[Dataset]:
    spec = registry.get(name)
    ctx = StageContext(stage=spec, params=spec.params.model_validate(params), slots={"recent": recent, **slots},
                       epoch=EpochInfo("E1", 1, "as-is", 0, tmp_path, "m"), rng=np.random.default_rng(0), seed=0,
                       log=logging.getLogger("test"))
    return spec.run(ctx)["recent"]


def test_voxel_mle_recovers_known_anisotropic_gaussians() -> None:
    rng = np.random.default_rng(4)
    rot = Rotation.from_euler("zyx", [0.7, 0.2, -0.4]).as_matrix()
    cov = rot @ np.diag([0.03, 0.01, 0.002]) ** 2 @ rot.T
    offset = np.array([634000.0, 4831000.0, 80.0])  # georeferenced: precision must survive
    centres = offset + np.array([[0.5, 0.5, 0.5], [2.5, 0.5, 0.5], [0.5, 3.5, 1.5]])  # voxel centres, edge 1
    clouds = [rng.multivariate_normal(c, cov, 40_000) for c in centres]
    mean, covs, counts = voxel_mle(np.concatenate(clouds), voxel=1.0, overlap_steps=1, min_points=10,
                                   min_sigma=1e-4)
    assert len(mean) == 3 and counts.sum() == 120_000
    for c, cloud in zip(centres, clouds, strict=True):
        i = np.argmin(np.linalg.norm(mean - c, axis=1))
        np.testing.assert_allclose(mean[i], cloud.mean(axis=0), atol=1e-9)
        np.testing.assert_allclose(covs[i], np.cov(cloud.T, bias=True), rtol=1e-6, atol=1e-12)
        # and against the truth: sampling error of covariance entries ~ sqrt(2/n) of their scale
        scale = np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
        assert np.all(np.abs(covs[i] - cov) / scale < 5 * np.sqrt(2 / 40_000))


def test_voxel_mle_overlap_and_flat_patches() -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 4, (20_000, 3))
    pts[:, 2] = 1.0  # a perfectly flat patch: singular covariances without the floor
    mean, cov, counts = voxel_mle(pts, voxel=1.0, overlap_steps=2, min_points=1, min_sigma=0.01)
    assert counts.sum() == 8 * len(pts)  # overlap 0.5: every point is in 2³ voxels
    w = np.linalg.eigvalsh(cov)
    assert np.all(w[:, 0] >= 0.01**2 * (1 - 1e-9)) and np.allclose(w[:, 0], 0.01**2)
    assert np.all(np.abs(mean[:, 2] - 1.0) < 1e-12)


def test_calibration_recovers_sigma(tmp_path: Path, registry) -> None:
    rng = np.random.default_rng(8)
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    sigma = 0.0005
    pts = trimesh.sample.sample_surface(mesh, 60_000, seed=3)[0] + rng.normal(0, sigma, (60_000, 3))
    strays = rng.uniform(-0.12, 0.12, (1_500, 3))  # 2.5 % stray points, as real scans have
    scan = np.vstack([pts, strays])
    ref = Dataset("ref", "as-designed", mesh.vertices, faces=mesh.faces)
    cal = calibrate(ref, [Dataset("scan", "as-is", scan)])
    assert cal.sigma == pytest.approx(sigma, rel=0.10)
    assert abs(cal.bias) < 0.2 * sigma
    # through the command line and into a workflow stage
    mesh.export(tmp_path / "ref.ply")
    write_points_ply(tmp_path / "scan.ply", scan)
    res = run_gdt("calibrate", "--reference", str(tmp_path / "ref.ply"), "--scan", str(tmp_path / "scan.ply"),
                  "--name", "sim", "-o", str(tmp_path / "profile.yaml"))
    assert res.returncode == 0, res.stderr
    profile = load_profile("profile.yaml", tmp_path)
    assert profile.isotropic_sigma("m") == pytest.approx(sigma, rel=0.10)
    assert profile.calibration["reference"]["sha256"] and profile.calibration["n_used"] == len(scan)
    out = _run(registry, "calibrated", {"profile": "profile.yaml"}, [Dataset("s", "as-is", pts[:10])], tmp_path)
    np.testing.assert_allclose(out[0].element_covariance()[0], np.eye(3) * profile.isotropic_sigma("m") ** 2)
    assert profile.isotropic_sigma("mm") == pytest.approx(1000 * profile.isotropic_sigma("m"))


@pytest.mark.skipif(not (SHARED_DATA / "stanford_bunny").is_dir(), reason="../shared/data/stanford_bunny not present")
def test_calibration_on_the_real_bunny_scans(registry) -> None:
    from gdt_pipeline.runner import read_dataset

    d = SHARED_DATA / "stanford_bunny"
    ref = read_dataset(d / "reconstruction" / "bun_zipper.ply", registry, name="ref", kind="mesh")
    scans = [read_dataset(d / "registered" / f"{n}_reg.ply", registry, name=n, kind="points")
             for n in ("bun000", "bun045", "bun090")]
    cal = calibrate(ref, scans)
    # the data README: median residual 0.05-0.075 mm; a Cyberware 3030 is a ~0.1 mm class scanner
    assert 0.04e-3 < cal.median_abs < 0.08e-3 and 0.05e-3 < cal.sigma < 0.15e-3


def test_sensor_model_axes_align_with_the_beam(tmp_path: Path, registry) -> None:
    rng = np.random.default_rng(2)
    # a plane x = 2 seen from the origin: incidence grows away from the centre
    yz = rng.uniform(-1.0, 1.0, (3_000, 2))
    pts = np.column_stack([np.full(len(yz), 2.0), yz])
    ds = Dataset("scan", "as-is", pts, viewpoints=[[0.0, 0.0, 0.0]])
    [out] = _run(registry, "sensor_model", {"profile": "tof_low_cost"}, [ds], tmp_path)
    cov = out.element_covariance()
    w, v = np.linalg.eigh(cov)
    beam = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    assert np.all(np.abs(np.einsum("ij,ij->i", v[:, :, 2], beam)) > 0.9999)  # largest axis along the beam
    rng_ = np.linalg.norm(pts, axis=1)
    cos = pts[:, 0] / rng_  # the plane's normal is x
    s_r, s_l = PRESETS["tof_low_cost"].sigmas(rng_, cos, "m")
    np.testing.assert_allclose(np.sqrt(w[:, 2]), s_r, rtol=1e-3)  # normals from 20 neighbours: nearly exact
    np.testing.assert_allclose(np.sqrt(w[:, :2]), np.column_stack([s_l, s_l]), rtol=1e-6)
    assert s_r.max() / s_r.min() > 1.3  # range and incidence both grow it
    with pytest.raises(ValueError, match="one sensor position per dataset"):
        _run(registry, "sensor_model", {"profile": "tof_low_cost"}, [Dataset("s", "as-is", pts)], tmp_path)


def test_registration_propagation_matches_monte_carlo(tmp_path: Path, registry) -> None:
    rng = np.random.default_rng(9)
    sig = np.array([2e-3, 1e-3, 3e-3, 0.004, 0.002, 0.001])  # rad, rad, rad, m, m, m
    cov_t = np.diag(sig**2)
    cov_t[0, 4] = cov_t[4, 0] = 0.5 * sig[0] * sig[4]
    pts = np.array([[3.0, 0.0, 0.0], [0.0, -2.0, 1.0], [1.0, 1.0, 1.0]])
    draws = rng.multivariate_normal(np.zeros(6), cov_t, 100_000)
    rots = Rotation.from_rotvec(draws[:, :3]).as_matrix()
    moved = np.einsum("mij,nj->mni", rots, pts) + draws[:, None, 3:]
    first_order = propagate_registration(pts, cov_t)
    for i in range(len(pts)):
        emp = np.cov(moved[:, i].T)
        scale = np.sqrt(np.outer(np.diag(first_order[i]), np.diag(first_order[i])))
        # sampling error ~ sqrt(2/N) of the scale; the first-order model drops terms of order σ_ω² (~1e-5)
        tol = 5 * np.sqrt(2 / 100_000) + 1e-3
        assert np.all(np.abs(emp - first_order[i]) / scale < tol), (i, emp, first_order[i])
    base = Dataset("s", "as-is", pts, uncertainty=GaussianUncertainty.isotropic(0.001))
    reg = Registration(np.eye(4), covariance=cov_t, method="test")
    [out] = _run(registry, "registration_propagation", {}, [base], tmp_path, registration=reg)
    np.testing.assert_allclose(out.element_covariance(), first_order + np.eye(3) * 1e-6, rtol=1e-12)


def test_voxel_mle_in_a_workflow(tmp_path: Path, registry) -> None:
    """Voxel Gaussians become the scan's elements in the twin, with their full covariances."""
    import shutil

    from pxr import Usd, UsdGeom

    from gdt_pipeline.runner import run_workflow
    from gdt_pipeline.simulation import make_test_scene

    from .conftest import REPO

    make_test_scene(tmp_path / "data" / "test_scene", seed=0)
    old = "  - uses: constant\n    role: as-is\n    with: {model: isotropic, sigma: 0.004}\n"
    text = (REPO / "workflows" / "demo.yaml").read_text()
    assert old in text
    new = "  - uses: voxel_mle\n    role: as-is\n    with: {voxel: 0.05, overlap: 0.5, min_points: 10}\n"
    text = text.replace(old, new)
    (tmp_path / "demo.yaml").write_text(text)
    shutil.rmtree(tmp_path / "twin", ignore_errors=True)
    twin = run_workflow(tmp_path / "demo.yaml", registry=registry, twin=tmp_path / "twin").twin
    stage = Usd.Stage.Open(str(twin / "twin.usda"))
    pv = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Twin/E1_tof_scan"))
    cov = np.asarray(pv.GetPrimvar("gdt:covariance").Get()).reshape(-1, 6)
    state = np.asarray(pv.GetPrimvar("gdt:changeState").Get())
    assert 1_000 < len(cov) < 26_590  # voxel Gaussians, not points
    assert np.ptp(cov[:, 0]) > 0  # anisotropic, per voxel
    assert 0.2 < (state == 1).mean() < 0.8  # the new cuboid's voxels come in as new
