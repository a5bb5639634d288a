"""The twin store, read back with plain pxr: a three-epoch twin round-trips exactly; later layers hold only
overrides; the stage at epoch K is what was written at K; errors name what is wrong."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdValidation

from twin_store import STATE_COLORS, ElementSet, TwinStore, TwinStoreError

UTM = np.array([634000.0, 4831000.0, 80.0])


def mesh_set(state: np.ndarray | None = None, visible: np.ndarray | None = None) -> ElementSet:
    """A small georeferenced pyramid mesh with box tolerances."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1.0]]) + UTM
    faces = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4], [0, 2, 1], [0, 3, 2]])
    n = len(faces)
    return ElementSet(key="E0_part", kind="mesh", points=verts, faces=faces, uncertainty_model="box",
                      covariance=None, half_widths=np.full((n, 3), 0.002), rotation=None,
                      uncertainty_summary=np.full(n, 0.002 / np.sqrt(3)),
                      state=np.zeros(n, np.uint8) if state is None else state, score=np.full(n, np.nan, np.float32),
                      source_epoch=np.zeros(n, np.int32), visible=np.ones(n, bool) if visible is None else visible)


def points_set(state: np.ndarray | None = None, visible: np.ndarray | None = None) -> ElementSet:
    """200 georeferenced points with full covariances and scores."""
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 1, (200, 3)) + UTM + [0, 0, 2]
    a = rng.normal(size=(200, 3, 3)) * 0.01
    cov = a @ np.swapaxes(a, 1, 2)
    iu = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))
    return ElementSet(key="E1_scan", kind="points", points=pts, faces=None, uncertainty_model="gaussian",
                      covariance=cov[:, iu[0], iu[1]], half_widths=None, rotation=None,
                      uncertainty_summary=np.sqrt(np.trace(cov, axis1=1, axis2=2) / 3),
                      state=np.ones(200, np.uint8) if state is None else state,
                      score=rng.uniform(0, 20, 200).astype(np.float32), source_epoch=np.ones(200, np.int32),
                      visible=np.ones(200, bool) if visible is None else visible)


@pytest.fixture
def twin(tmp_path: Path) -> tuple[Path, dict[str, list[ElementSet]]]:
    store = TwinStore.create(tmp_path / "twin", meters_per_unit=0.001, up_axis="Y")
    e0 = [mesh_set()]
    e1 = [mesh_set(), points_set()]
    removed = np.zeros(6, bool)
    removed[[1, 4]] = True
    st = np.where(removed, 2, 0).astype(np.uint8)
    pstate = np.zeros(200, np.uint8)
    pstate[:10] = 1
    e2 = [mesh_set(state=st, visible=~removed), points_set(state=pstate, visible=np.arange(200) >= 5)]
    for eid, elems in (("E0", e0), ("E1", e1), ("E2", e2)):
        store.write_epoch(eid, elems, {"epoch": eid, "stages": [{"uses": "x", "params": {"tau": 1.5}}]})
    return tmp_path / "twin", {"E0": e0, "E1": e1, "E2": e2}


def test_plain_pxr_reads_back_every_array(twin) -> None:
    path, written = twin
    stage = Usd.Stage.Open(str(path / "twin.usda"))
    assert list(stage.GetRootLayer().subLayerPaths) == ["epochs/E2.usdc", "epochs/E1.usdc", "epochs/E0.usdc"]
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.001 and UsdGeom.GetStageUpAxis(stage) == "Y"
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/Twin")
    mesh_prim, pts_prim = stage.GetPrimAtPath("/Twin/E0_part"), stage.GetPrimAtPath("/Twin/E1_scan")
    mesh, pts = UsdGeom.Mesh(mesh_prim), UsdGeom.Points(pts_prim)
    m, p = written["E2"]
    xf = UsdGeom.Xformable(mesh_prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    world = np.array([xf.Transform(v) for v in mesh.GetPointsAttr().Get()])
    np.testing.assert_allclose(world, m.points, atol=1e-6)  # float32 local + double translate keeps UTM precision
    assert np.array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), m.faces)
    assert mesh.GetSubdivisionSchemeAttr().Get() == "none"
    assert list(mesh.GetHoleIndicesAttr().Get()) == [1, 4]
    api = UsdGeom.PrimvarsAPI(mesh_prim)
    assert np.array_equal(np.asarray(api.GetPrimvar("gdt:changeState").Get()), m.state)
    assert api.GetPrimvar("gdt:changeState").GetInterpolation() == "uniform"
    assert api.GetPrimvar("gdt:uncertaintyModel").Get() == "box"
    np.testing.assert_allclose(np.asarray(api.GetPrimvar("gdt:halfWidths").Get()), m.half_widths, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(api.GetPrimvar("displayColor").Get()), STATE_COLORS[m.state])
    papi = UsdGeom.PrimvarsAPI(pts_prim)
    cov = papi.GetPrimvar("gdt:covariance")
    assert cov.GetElementSize() == 6 and cov.GetInterpolation() == "vertex"
    assert "xx xy xz yy yz zz" in cov.GetAttr().GetDocumentation()
    np.testing.assert_allclose(np.asarray(cov.Get()).reshape(-1, 6), p.covariance, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(papi.GetPrimvar("gdt:changeScore").Get()), p.score)
    assert np.array_equal(np.asarray(papi.GetPrimvar("gdt:changeState").Get()), p.state)
    assert np.array_equal(np.asarray(papi.GetPrimvar("gdt:visible").Get()), p.visible)
    assert np.array_equal(np.asarray(pts.GetIdsAttr().Get()), np.arange(200))
    assert pts.GetWidthsInterpolation() == "vertex"
    widths = np.asarray(pts.GetWidthsAttr().Get())
    assert np.all(widths[:5] == 0) and np.all(widths[5:] > 0)  # hidden points have zero width in any viewer


def test_later_layers_hold_only_overrides(twin) -> None:
    path, _ = twin
    e2 = Sdf.Layer.FindOrOpen(str(path / "epochs" / "E2.usdc"))
    assert e2.GetAttributeAtPath("/Twin/E0_part.points") is None
    assert e2.GetAttributeAtPath("/Twin/E0_part.faceVertexIndices") is None
    assert e2.GetPrimAtPath("/Twin/E0_part").specifier == Sdf.SpecifierOver
    state = e2.GetAttributeAtPath("/Twin/E0_part.primvars:gdt:changeState")
    assert state is not None and state.typeName == Sdf.ValueTypeNames.UCharArray and not state.custom
    assert state.GetInfo("interpolation") == "uniform"  # restated in the layer that writes it
    assert e2.GetAttributeAtPath("/Twin/E0_part.primvars:gdt:halfWidths") is None  # unchanged: not restated
    e1 = Sdf.Layer.FindOrOpen(str(path / "epochs" / "E1.usdc"))
    assert e1.GetPrimAtPath("/Twin/E0_part") is None  # nothing changed about the mesh in E1
    assert e1.GetPrimAtPath("/Twin/E1_scan").specifier == Sdf.SpecifierDef


def test_stage_at_epoch_k_is_what_was_written_at_k(twin) -> None:
    path, written = twin
    store = TwinStore.open(path)
    assert store.epochs() == ["E0", "E1", "E2"]
    for eid, elems in written.items():
        got = {e.key: e for e in store.read_epoch(eid)}
        assert set(got) == {e.key for e in elems}
        for want in elems:
            g = got[want.key]
            np.testing.assert_allclose(g.points, want.points, atol=1e-6)
            for name in ("state", "visible", "source_epoch"):
                assert np.array_equal(getattr(g, name), getattr(want, name)), (eid, want.key, name)
            np.testing.assert_array_equal(g.score, want.score.astype(np.float32))
    assert store.provenance("E2")["stages"][0]["params"] == {"tau": 1.5}
    data = Sdf.Layer.FindOrOpen(str(path / "epochs" / "E1.usdc")).customLayerData["gdt"]
    assert json.loads(data["provenance_json"])["epoch"] == "E1"
    assert list(data["state_names"]) == ["unchanged", "new", "removed", "outside_rov", "not_comparable"]


def test_errors_name_what_is_wrong(twin) -> None:
    path, written = twin
    store = TwinStore.open(path)
    with pytest.raises(TwinStoreError, match="epoch 'E1' is already in the twin"):
        store.write_epoch("E1", written["E2"], {})
    with pytest.raises(TwinStoreError, match="element sets \\['E1_scan'\\] of earlier epochs are missing"):
        store.write_epoch("E3", [written["E2"][0]], {})
    moved = mesh_set()
    moved = ElementSet(**{**moved.__dict__, "points": moved.points + 0.01})
    with pytest.raises(TwinStoreError, match="geometry of an existing element set cannot change: E0_part"):
        store.write_epoch("E3", [moved, written["E2"][1]], {})
    with pytest.raises(TwinStoreError, match="'bad key' is not a valid USD identifier"):
        ElementSet(**{**mesh_set().__dict__, "key": "bad key"})
    with pytest.raises(TwinStoreError, match="E0_part: state must have shape"):
        ElementSet(**{**mesh_set().__dict__, "state": np.zeros(3, np.uint8)})
    assert store.epochs() == ["E0", "E1", "E2"]  # failed writes left nothing behind
    assert sorted(p.name for p in (path / "epochs").iterdir()) == ["E0.usdc", "E1.usdc", "E2.usdc"]
    with pytest.raises(TwinStoreError, match="already exists"):
        TwinStore.create(path)
    with pytest.raises(TwinStoreError, match="is not a twin"):
        TwinStore.open(path / "epochs")


def test_usd_validation_finds_no_errors(twin) -> None:
    path, _ = twin
    registry = UsdValidation.ValidationRegistry()
    ctx = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    stage = Usd.Stage.Open(str(path / "twin.usda"))
    errors = [e.GetMessage() for e in ctx.Validate(stage)
              if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert not errors
    flat = Usd.Stage.Open(stage.Flatten())
    assert not [e for e in ctx.Validate(flat) if e.GetType() == UsdValidation.ValidationErrorType.Error]


def test_sets_made_on_demand_are_made_one_at_a_time_and_written_as_the_sets_themselves(tmp_path: Path) -> None:
    """An epoch handed as sets made on demand is written as the same sets handed as a list; the writer checks the keys
    without making a set, makes each once, and a set made with another key than announced is an error."""
    from twin_store import SetsOnDemand, set_keys

    sets = [mesh_set(), points_set()]
    made: list[int] = []

    def make(i: int) -> ElementSet:
        made.append(i)
        return sets[i]

    lazy = SetsOnDemand([s.key for s in sets], make)
    assert set_keys(lazy) == ["E0_part", "E1_scan"] and made == []
    listed = TwinStore.create(tmp_path / "listed")
    listed.write_epoch("E0", sets, {})
    on_demand = TwinStore.create(tmp_path / "on_demand")
    on_demand.write_epoch("E0", lazy, {})
    assert made == [0, 1]
    for want, got in zip(listed.read_epoch("E0"), on_demand.read_epoch("E0"), strict=True):
        assert got.key == want.key
        assert np.array_equal(got.points, want.points) and np.array_equal(got.state, want.state)
        assert np.allclose(got.uncertainty_summary, want.uncertainty_summary)
        if want.covariance is not None:
            assert np.allclose(got.covariance, want.covariance)
    wrong = SetsOnDemand(["E0_part", "other"], lambda i: sets[i])
    with pytest.raises(ValueError, match="element set 1: made with key 'E1_scan', announced as 'other'"):
        list(wrong)
    with pytest.raises(IndexError):
        lazy[2]
    assert [s.key for s in lazy[::-1]] == ["E1_scan", "E0_part"]
