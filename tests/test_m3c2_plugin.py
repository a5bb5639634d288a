"""The gdt-m3c2 plugin: py4dgeo's M3C2 as the distance stage ``m3c2``, built on the public measures API. Its
per-point results in a workflow equal py4dgeo's called directly on the same arrays; against a CAD mesh the
reference is the composite sampled on its facets with the stage's generator."""

from __future__ import annotations

import logging
import textwrap
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gdt_pipeline import Composite, CompositeItem, Dataset, EpochInfo, StageContext

from .conftest import CubeScene, write_points_ply

py4dgeo = pytest.importorskip("py4dgeo")

PARAMS = {"cyl_radius": 0.08, "normal_radii": [0.15], "max_distance": 0.5}
WORKFLOW = """\
name: m3c2
twin: twin
seed: 3
epochs:
  - id: E0
    role: as-is
    inputs: [{path: before.ply, name: before}]
  - id: E1
    role: as-is
    inputs: [{path: scan.ply, name: scan}]
stages:
  - uses: m3c2
    epochs: [E1]
    with: {cyl_radius: 0.08, normal_radii: [0.15], max_distance: 0.5}
  - uses: significance
    epochs: [E1]
    with: {alpha: 0.05}
  - uses: keep_unchanged
"""


def _direct(reference: np.ndarray, recent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """py4dgeo's M3C2 called as its documentation shows, every recent point a core point; NaN where it finds no
    normal (fewer than 3 reference points within the normal radius: py4dgeo leaves those normals uninitialised)."""
    logging.getLogger("py4dgeo").setLevel(logging.WARNING)  # py4dgeo logs each KD-tree to ./py4dgeo.log
    algo = py4dgeo.M3C2(epochs=(py4dgeo.Epoch(reference), py4dgeo.Epoch(recent)), corepoints=recent, **PARAMS)
    distance, uncertainty = algo.run()
    lod = uncertainty["lodetection"].copy()
    no_normal = np.array([len(n) < 3 for n in cKDTree(reference).query_ball_point(recent, PARAMS["normal_radii"][0])])
    distance[no_normal], lod[no_normal] = np.nan, np.nan
    return distance, lod


def _read(path: Path) -> np.ndarray:
    import open3d as o3d

    pcd = o3d.io.read_point_cloud(str(path))
    return np.array(pcd.points, dtype=np.float64)  # a copy: the cloud is freed on return


def test_m3c2_in_a_workflow_equals_py4dgeo(cube_scene: CubeScene, registry) -> None:
    import trimesh
    from pxr import Usd, UsdGeom

    from gdt_pipeline.runner import run_workflow

    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cube.apply_translation((0, 0, 0.5))
    before = trimesh.sample.sample_surface(cube, 4000, seed=5)[0]
    before += np.random.default_rng(5).normal(0, cube_scene.sigma, before.shape)
    write_points_ply(cube_scene.dir / "before.ply", before)
    wf = cube_scene.dir / "m3c2.yaml"
    wf.write_text(textwrap.dedent(WORKFLOW))
    twin = run_workflow(wf, registry=registry).twin

    stage = Usd.Stage.Open(str(twin / "twin.usda"))
    primvars = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Twin/E1_scan"))
    score = np.asarray(primvars.GetPrimvar("gdt:changeScore").Get(), dtype=np.float64)
    p_value = np.asarray(primvars.GetPrimvar("gdt:pValue").Get(), dtype=np.float64)
    state = np.asarray(primvars.GetPrimvar("gdt:changeState").Get())

    # the reference is the twin's E0 as it stores it (float32 about the set's origin): what E1 was handed
    from twin_store import TwinStore

    [stored] = TwinStore.open(twin).read_epoch("E0")
    assert np.max(np.abs(stored.points - _read(cube_scene.dir / "before.ply"))) < 1e-7
    distance, lod = _direct(stored.points, _read(cube_scene.scan))
    want = np.abs(distance) / lod
    assert np.array_equal(np.isnan(score), np.isnan(want))
    np.testing.assert_allclose(score, want, rtol=1e-6, equal_nan=True)  # the twin stores float32
    from scipy.stats import norm

    np.testing.assert_allclose(p_value, 2 * norm.sf(1.96 * want), rtol=1e-5, atol=1e-30, equal_nan=True)
    assert np.array_equal(state == 1, ~(p_value >= 0.05))
    # real values: the cube is unchanged (about 5 % above the 95 % LoD), the new box is change
    truth = cube_scene.changed
    assert (state[~truth] == 1).mean() < 0.1
    assert (state[truth] == 1).mean() > 0.9


def test_m3c2_against_a_cad_mesh_samples_the_composite(cube_scene: CubeScene, registry) -> None:
    import trimesh

    from gdt_pipeline.geometry import sample_surface
    from gdt_pipeline.measures import reference_cloud

    mesh = trimesh.load(cube_scene.cad, force="mesh")
    cad = Dataset("cad", "as-designed", np.asarray(mesh.vertices), faces=np.asarray(mesh.faces))
    n = cad.n_elements
    comp = Composite((CompositeItem("E0_cad", cad, "E0", np.zeros(n), np.full(n, np.nan), np.zeros(n),
                                    np.ones(n, bool)),))
    scan = Dataset("scan", "as-is", _read(cube_scene.scan))
    spec = registry.get("m3c2")
    params = spec.params.model_validate({**PARAMS, "mesh_spacing": 0.02})
    ctx = StageContext(stage=spec, params=params, slots={"recent": [scan], "reference": comp},
                       epoch=EpochInfo("E1", 1, "as-is", 0, Path("."), "m"), rng=np.random.default_rng(9), seed=9,
                       log=logging.getLogger("test"))
    [s] = spec.run(ctx)["scores"]

    reference = reference_cloud(comp, 0.02, np.random.default_rng(9))
    assert len(reference) == ctx.notes["reference_points"] and len(reference) > 6 / 0.02**2 * 0.9
    assert np.array_equal(sample_surface(cad, 0.02, np.random.default_rng(9)), reference)  # one visible item
    distance, lod = _direct(reference, np.array(scan.points))  # py4dgeo wants a writeable array
    np.testing.assert_array_equal(s.score, np.abs(distance) / lod)
    assert s.measure == "m3c2" and s.simulate is None
    assert ctx.notes["no_distance"] == int(np.isnan(distance).sum())
