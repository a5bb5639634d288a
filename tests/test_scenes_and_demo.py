"""The generated test scene (truth, noise model, occlusion, determinism) and the demo workflow's detection quality
against that ground truth."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from gdt_pipeline.runner import run_workflow
from gdt_pipeline.simulation import make_test_scene, scene_objects

from .conftest import REPO


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ts") / "data" / "test_scene"
    make_test_scene(root, seed=0)
    return root


def test_scene_truth_noise_and_occlusion(scene: Path) -> None:
    import open3d as o3d
    import trimesh

    truth = np.load(scene / "truth_E1.npz")
    pts = np.asarray(o3d.io.read_point_cloud(str(scene / "scan_E1.ply")).points)
    clean, obj, changed, view = truth["clean"], truth["object_id"], truth["changed"], truth["viewpoint"]
    names = list(truth["object_names"])
    assert 20_000 < len(pts) == len(clean) < 120_000
    assert 0.1 < changed.mean() < 0.6
    assert np.array_equal(changed, obj == names.index("large_cuboid"))
    for name in ("small_cuboid", "frustum_a", "frustum_b"):
        mesh = trimesh.load(scene / f"cad_{name}.obj", force="mesh")
        assert mesh.is_watertight
    objects = scene_objects()
    # clean positions lie on the as-is surfaces; changed ones are off every CAD surface
    rs = o3d.t.geometry.RaycastingScene()
    for mesh, _ in objects.values():
        rs.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                         o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    assert rs.compute_distance(o3d.core.Tensor(clean.astype(np.float32))).numpy().max() < 1e-5
    cad = o3d.t.geometry.RaycastingScene()
    for mesh, in_cad in objects.values():
        if in_cad:
            cad.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                              o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    d_cad = cad.compute_distance(o3d.core.Tensor(clean.astype(np.float32))).numpy()
    assert np.all(d_cad[changed] > 1e-3) and np.all(d_cad[~changed] < 1e-5)
    # anisotropic noise: 4 mm along the beam, 4/3 mm across it
    import json

    vps = np.array(json.loads((scene / "scene.json").read_text())["viewpoints"]["E1"])
    beam = clean - vps[view]
    rng_ = np.linalg.norm(beam, axis=1)
    beam /= rng_[:, None]
    res = pts - clean
    along = np.einsum("ij,ij->i", res, beam)
    lateral = res - along[:, None] * beam
    assert np.std(along) == pytest.approx(0.004, rel=0.05)
    assert np.sqrt(np.mean(np.sum(lateral**2, axis=1)) / 2) == pytest.approx(0.004 / 3, rel=0.05)
    # occlusion is real: from its viewpoint, the first hit along the ray is the point itself
    rays = np.hstack([vps[view], beam]).astype(np.float32)
    t_hit = rs.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    np.testing.assert_allclose(t_hit, rng_, atol=1e-4)


def test_scene_is_deterministic(tmp_path: Path, scene: Path) -> None:
    again = make_test_scene(tmp_path / "again", seed=0)
    for name in ("scan_E1.ply", "truth_E1.npz", "cad_frustum_a.obj", "scene.json"):
        a = hashlib.sha256((scene / name).read_bytes()).hexdigest()
        b = hashlib.sha256((again.root / name).read_bytes()).hexdigest()
        assert a == b, name
    other = make_test_scene(tmp_path / "other", seed=1)
    assert (other.root / "scan_E1.ply").read_bytes() != (scene / "scan_E1.ply").read_bytes()


def test_demo_workflow_detects_the_new_cuboid(tmp_path: Path, scene: Path, registry) -> None:
    wf = scene.parent.parent / "demo.yaml"
    shutil.copy(REPO / "workflows" / "demo.yaml", wf)
    result = run_workflow(wf, registry=registry, twin=tmp_path / "twin")
    stage = Usd.Stage.Open(str(result.twin / "twin.usda"))
    pv = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Twin/E1_tof_scan"))
    state = np.asarray(pv.GetPrimvar("gdt:changeState").Get())
    visible = np.asarray(pv.GetPrimvar("gdt:visible").Get())
    truth = np.load(scene / "truth_E1.npz")["changed"]
    pred = state == 1
    tp = np.sum(pred & truth)
    precision, recall = tp / pred.sum(), tp / truth.sum()
    f1 = 2 * precision * recall / (precision + recall)
    assert f1 > 0.98, (precision, recall)
    assert np.array_equal(visible, pred)  # only the new elements come into the composite
    colors = np.asarray(pv.GetPrimvar("displayColor").Get())
    np.testing.assert_allclose(colors[pred], [[0.1, 0.75, 0.2]] * int(pred.sum()), atol=1e-6)
    for name in ("small_cuboid", "frustum_a", "frustum_b"):
        cad = UsdGeom.Mesh(stage.GetPrimAtPath(f"/Twin/E0_cad_{name}"))
        assert cad and len(cad.GetHoleIndicesAttr().Get() or []) == 0
