"""Region of view: frusta, Plane-of-Sight occlusion by parity, and removal versus "outside the region of view"."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from gdt_pipeline import ChangeState, Composite, Dataset, GaussianUncertainty, RegionOfView
from gdt_pipeline.plugins import load_registry
from tests.rov_helpers import cad_item, stage_ctx


@pytest.fixture(scope="module")
def registry():
    return load_registry()


def _plane_mesh(x: float, half: float, n: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """An open (non-watertight) square mesh in the plane x = const, facing -x."""
    g = np.linspace(-half, half, n + 1)
    yy, zz = np.meshgrid(g, g, indexing="ij")
    verts = np.column_stack([np.full(yy.size, x), yy.ravel(), zz.ravel()])
    idx = np.arange(verts.shape[0]).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.vstack([np.column_stack([a, c, b]), np.column_stack([a, d, c])])
    return verts, faces


def _scan(points: np.ndarray, eye: np.ndarray, name: str = "scan") -> Dataset:
    cov = np.broadcast_to(np.eye(3) * 1e-8, (len(points), 3, 3))
    return Dataset(name, "as-is", points, viewpoints=eye[None, :]).with_uncertainty(GaussianUncertainty(cov))


def _grid(x: float, y0: float, y1: float, z0: float, z1: float, step: float) -> np.ndarray:
    y, z = np.meshgrid(np.arange(y0, y1, step), np.arange(z0, z1, step), indexing="ij")
    return np.column_stack([np.full(y.size, x), y.ravel(), z.ravel()])


def test_contains_is_the_union_of_overlapping_closed_parts() -> None:
    a, b = trimesh.creation.box(extents=(2, 2, 2)), trimesh.creation.box(extents=(2, 2, 2))
    b.apply_translation((1, 0, 0))
    rov = RegionOfView(np.vstack([a.vertices, b.vertices]), np.vstack([a.faces, b.faces + len(a.vertices)]),
                       (len(a.faces), len(b.faces)))
    inside = rov.contains(np.array([[0.5, 0, 0], [-0.9, 0, 0], [1.9, 0, 0], [3.0, 0, 0]]))
    # (0.5, 0, 0) lies in both boxes: one scene over both would call it outside by parity
    assert inside.tolist() == [True, True, True, False]


@pytest.mark.parametrize("sight", ["depth", "plane"])
def test_removed_object_in_view_is_removed_and_an_object_hidden_behind_another_stays_outside(registry, tmp_path,
                                                                                             sight) -> None:
    eye = np.array([0.0, 0.0, 0.0])
    # reference: a cube A that was removed (in front, in plain view) and a cube B hidden behind a wall W that the
    # recent scan measured; B is gone too, but nobody could have seen that
    cube_a = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    cube_a.apply_translation((1.5, -0.6, 0))
    cube_b = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    cube_b.apply_translation((3.0, 0.6, 0))
    back = trimesh.Trimesh(*_plane_mesh(4.0, 1.5), process=False)  # a backdrop that is still there
    reference = Composite((cad_item("E0_a", cube_a), cad_item("E0_b", cube_b), cad_item("E0_back", back)))
    # recent: a wall at x = 2 in front of B (non-watertight: an open point grid) and the backdrop
    wall = _grid(2.0, 0.2, 1.0, -0.4, 0.4, 0.01)
    backdrop = _grid(4.0, -1.5, 1.5, -1.5, 1.5, 0.02)
    backdrop = backdrop[~((backdrop[:, 1] > 0.2 * 2) & (np.abs(backdrop[:, 2]) < 0.4 * 2))]  # the wall's shadow
    scan = _scan(np.vstack([wall, backdrop]), eye)
    ctx = stage_ctx(registry, "manual_box", {"lower": [0.5, -2, -2], "upper": [5, 2, 2], "sight": sight}, [scan],
               reference, tmp_path)
    rov = registry.get("manual_box").run(ctx)["rov"]
    view_a, view_b = rov.views["E0_a"].in_view, rov.views["E0_b"].in_view
    facing = np.einsum("ij,ij->i", cube_a.face_normals, eye - cube_a.triangles_center) > 0  # look at the sensor
    assert view_a[facing].all() and not view_a[~facing].any()
    assert not view_b.any()  # behind the wall: occluded (one crossing of the wall's measured surface)
    assert not rov.views["E0_a"].matched[view_a].any()
    assert rov.views["E0_back"].matched[rov.views["E0_back"].in_view].mean() > 0.95
    fusion = registry.get("keep_unchanged")
    fctx = stage_ctx(registry, "keep_unchanged", {}, [scan], reference, tmp_path)
    fctx.slots["rov"] = rov
    fctx.slots["change"] = []
    # the fusion demands a change per recent dataset once a reference exists: give the scan "unchanged"
    from gdt_pipeline import Change

    n = scan.n_elements
    fctx.slots["change"] = [Change(query=0, score=np.zeros(n), mask=np.zeros(n, bool),
                                   state=np.zeros(n, np.uint8))]
    items = {it.key: it for it in fusion.run(fctx)["composite"].items}
    assert np.all(items["E0_a"].state[facing] == ChangeState.REMOVED)
    assert not items["E0_a"].visible[facing].any()
    if sight == "depth":  # judged by area: the cube was seen through wholly, so its far faces went with it
        assert np.all(items["E0_a"].state == ChangeState.REMOVED) and not items["E0_a"].visible.any()
    assert np.all(items["E0_b"].state == ChangeState.OUTSIDE_ROV) and items["E0_b"].visible.all()


def test_parity_on_a_non_watertight_mesh_and_two_disconnected_components(registry, tmp_path) -> None:
    eye = np.array([0.0, 0.0, 0.0])
    target = trimesh.Trimesh(*_plane_mesh(5.0, 0.5, 4), process=False)
    reference = Composite((cad_item("E0_t", target),))
    for layers, hidden in (((2.0,), True), ((2.0, 3.0), False)):
        # recent data: one or two open sheets between the sensor and the target (as meshes: no reconstruction)
        recent = []
        for k, x in enumerate(layers):
            v, f = _plane_mesh(x, 1.0)
            recent.append(Dataset(f"sheet{k}", "as-is", v, faces=f, viewpoints=eye[None, :]).with_uncertainty(
                GaussianUncertainty(np.broadcast_to(np.eye(3) * 1e-8, (len(f), 3, 3)))))
        box = {"lower": [0.5, -2, -2], "upper": [6, 2, 2], "sight": "plane"}
        ctx = stage_ctx(registry, "manual_box", box, recent, reference, tmp_path)
        view = registry.get("manual_box").run(ctx)["rov"].views["E0_t"].in_view
        # one crossing: odd, hidden; two disconnected sheets: even, in view by the paper's parity rule
        assert (not view.any()) if hidden else view.all()
        ctx = stage_ctx(registry, "manual_box", {**box, "rule": "any"}, recent, reference, tmp_path)
        assert not registry.get("manual_box").run(ctx)["rov"].views["E0_t"].in_view.any()


def test_sensor_frustum_from_the_pose_file(registry, tmp_path) -> None:
    import json

    from gdt_pipeline.runner import read_pose_file

    eye, target = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    (tmp_path / "s_pose.json").write_text(json.dumps({"viewpoint": eye.tolist(), "target": target.tolist(),
                                                      "scanner": {"kind": "pinhole", "fov_deg": 60.0,
                                                                  "aspect": 2.0, "max_range": 5.0}}))
    scan = _scan(_grid(3.0, -0.5, 0.5, -0.3, 0.3, 0.02), eye)
    # the station the engine settles on reading (runner.poses), as every stage sees it
    scan = Dataset(scan.name, "as-is", scan.points, uncertainty=scan.uncertainty, viewpoints=scan.viewpoints,
                   pose=read_pose_file(tmp_path / "s_pose.json"))
    ctx = stage_ctx(registry, "sensor_frustum", {"occlusion": False}, [scan], Composite(), tmp_path)
    rov = registry.get("sensor_frustum").run(ctx)["rov"]
    # horizontal half-angle 30°, vertical atan(tan 30° / 2) = 16.1°, range 0.05 .. 5
    pts = np.array([[4.0, 4.0 * np.tan(np.radians(29)), 0], [4.0, 4.0 * np.tan(np.radians(31)), 0],
                    [4.0, 0, 4.0 * np.tan(np.radians(15.5))], [4.0, 0, 4.0 * np.tan(np.radians(16.7))],
                    [4.9, 0, 0], [5.1, 0, 0], [-1.0, 0, 0]])
    assert rov.contains(pts).tolist() == [True, False, True, False, True, False, False]


def test_the_region_of_view_is_stored_with_its_epoch_and_read_back_with_pxr(tmp_path) -> None:
    from pxr import Usd, UsdGeom

    from twin_store import TwinStore

    box = RegionOfView.box([0, 0, 0], [1, 2, 3])
    store = TwinStore.create(tmp_path / "twin")
    store.write_epoch("E0", [], {"note": "no elements"}, region_of_view=(box.vertices, box.faces))
    store.write_epoch("E1", [], {"note": "no region"})
    pts, faces = store.read_region_of_view("E0")
    np.testing.assert_allclose(pts, box.vertices, atol=1e-6)
    np.testing.assert_array_equal(faces, box.faces)
    stage = Usd.Stage.Open(str(tmp_path / "twin" / "twin.usda"))
    prim = stage.GetPrimAtPath("/RegionsOfView/E0")
    assert prim and UsdGeom.Imageable(prim).GetPurposeAttr().Get() == UsdGeom.Tokens.guide
    assert store.read_region_of_view("E1") is None or store.read_region_of_view("E1")[0].shape == (0, 3)


def test_sight_to_the_stations_where_the_plane_of_sight_cuts_through_the_scene(registry, tmp_path) -> None:
    # station A looks at a removed cube's -x face along a clear line; station B, off to the side, makes the Plane of
    # Sight the segment AB, and the sight ray from that face to AB runs through a plate B measured: the paper's rule
    # calls the face hidden, the station rule sees it from A and calls it removed
    a, b = np.array([-2.0, 0.0, 0.0]), np.array([2.0, 3.0, 0.0])
    cube = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    reference = Composite((cad_item("E0_cube", cube),))
    x, z = np.meshgrid(np.arange(-0.8, -0.2, 0.01), np.arange(-0.3, 0.3, 0.01), indexing="ij")
    plate = np.column_stack([x.ravel(), np.full(x.size, 0.45), z.ravel()])
    recent = [_scan(_grid(3.0, -1, 1, -1, 1, 0.02), a, "seen_from_a"), _scan(plate, b, "seen_from_b")]
    face = np.flatnonzero(cube.face_normals[:, 0] < -0.9)
    box = {"lower": [-1, -1, -1], "upper": [1, 1, 1]}
    views = {}
    for sight in ("plane", "stations", "depth"):
        ctx = stage_ctx(registry, "manual_box", {**box, "sight": sight}, recent, reference, tmp_path)
        rov = registry.get("manual_box").run(ctx)["rov"]
        views[sight] = rov.views["E0_cube"].in_view
        assert not rov.views["E0_cube"].matched[views[sight]].any()
    assert not views["plane"][face].any()
    assert views["stations"][face].all()
    assert views["depth"][face].all()  # A saw the far wall through the face's place
    # the faces no station faces stay out of view either way
    away = np.flatnonzero(np.all(np.einsum("ij,sij->si", cube.face_normals,
                                           np.stack([a, b])[:, None, :] - cube.triangles_center[None]) <= 0, axis=0))
    assert away.size and not views["stations"][away].any()


def test_a_confirmed_thin_part_hides_the_face_right_behind_it(registry, tmp_path) -> None:
    # a 4 mm plate, measured on its front, covers a cube's face that touches its back (a frame web behind its
    # flange); the measured surface's rays start 3 cm out (3 × a 1 cm point spacing), past the plate: only the plate's
    # CAD facets, confirmed by the scan, hide the face
    eye = np.array([0.0, 0.0, 0.0])
    plate = trimesh.creation.box(extents=(0.004, 0.6, 0.6))
    plate.apply_translation((2.002, 0, 0))
    cube = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    cube.apply_translation((2.104, 0, 0))
    reference = Composite((cad_item("E0_plate", plate), cad_item("E0_cube", cube)))
    scan = _scan(_grid(2.0, -0.3, 0.3, -0.3, 0.3, 0.01), eye)
    front = np.flatnonzero(cube.face_normals[:, 0] < -0.9)
    views = {}
    for confirmed in (False, True):
        ctx = stage_ctx(registry, "manual_box", {"lower": [1, -1, -1], "upper": [3, 1, 1], "sight": "plane",
                                            "confirmed_occlude": confirmed}, [scan], reference, tmp_path)
        rov = registry.get("manual_box").run(ctx)["rov"]
        views[confirmed] = rov.views["E0_cube"].in_view[front]
        assert rov.views["E0_plate"].matched[plate.face_normals[:, 0] < -0.9].all()
    assert views[False].all() and not views[True].any()
    # a depth image needs no such help: the plate's measured surface stands 4 mm (40 σ) in front of the face
    ctx = stage_ctx(registry, "manual_box", {"lower": [1, -1, -1], "upper": [3, 1, 1]}, [scan], reference, tmp_path)
    assert not registry.get("manual_box").run(ctx)["rov"].views["E0_cube"].in_view[front].any()
