"""Large point sets in parts, each part in a payload layer: read back whole and exact, loaded on demand by a viewer
that opens the twin unloaded (it then sees only the decimated preview), overridden by later epochs part by part,
checked against their sha256, and movable with the twin; a set written in one payload layer before parts still
reads and takes later epochs."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom

import twin_store.parts as parts
import twin_store.payloads as payloads
from twin_store import STATE_COLORS, ElementSet, RowsOnDemand, TwinStore, TwinStoreError
from twin_store.elements import define_element_set

from .test_twin_store import mesh_set, points_set


@pytest.fixture
def big_twin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, dict]:
    # 200 points count as "large" here, in parts of 64, 64, 64 and 8 rows, and the preview keeps every 4th of them
    monkeypatch.setattr(payloads, "PAYLOAD_ELEMENTS", 100)
    monkeypatch.setattr(parts, "PART_ELEMENTS", 64)
    monkeypatch.setattr(payloads, "PREVIEW_POINTS", 50)
    store = TwinStore.create(tmp_path / "twin")
    state = np.zeros(200, np.uint8)
    state[:40] = 1
    epochs = {"E0": [mesh_set()], "E1": [mesh_set(), points_set()], "E2": [mesh_set(), points_set(state=state,
                                                                                   visible=np.arange(200) >= 20)]}
    for eid, sets in epochs.items():
        store.write_epoch(eid, sets, {"epoch": eid})
    return tmp_path / "twin", epochs


PARTS = [f"part_{i:04d}" for i in range(4)]


def test_a_large_set_lives_in_parts_of_their_own_layers_and_reads_back_exactly(big_twin: tuple[Path, dict]) -> None:
    twin, epochs = big_twin
    assert sorted(p.name for p in (twin / "epochs").iterdir()) == sorted(
        ["E0.usdc", "E1.usdc", "E2.usdc", *(f"E1.E1_scan.{part}.usdc" for part in PARTS)])
    store = TwinStore.open(twin)
    for eid, written in epochs.items():
        got = {es.key: es for es in store.read_epoch(eid)}
        for es in written:
            back = got[es.key]
            assert np.allclose(back.points, es.points, rtol=0, atol=1e-4)
            assert np.array_equal(back.state, es.state) and np.array_equal(back.visible, es.visible)
            assert np.allclose(back.score, es.score, equal_nan=True)
            if es.kind == "points":
                assert np.array_equal(back.ids, np.arange(200))
                assert np.allclose(back.covariance, es.covariance, rtol=1e-6, atol=1e-12)
                assert np.allclose(back.uncertainty_summary, es.uncertainty_summary, rtol=1e-6)
                assert back.uncertainty_model == "gaussian"
    # the epoch layer holds the set's origin and one arc per part, not the points
    layer = Sdf.Layer.FindOrOpen(str(twin / "epochs" / "E1.usdc"))
    spec = layer.GetPrimAtPath(Sdf.Path("/Twin/E1_scan"))
    assert spec.typeName == "Xform" and not spec.payloadList.prependedItems
    assert [child.name for child in spec.nameChildren] == PARTS
    for child in spec.nameChildren:
        assert [p.assetPath for p in child.payloadList.prependedItems] == [f"./E1.E1_scan.{child.name}.usdc"]
        assert not child.attributes
    stage = Usd.Stage.Open(str(twin / "twin.usda"))
    sizes = [len(UsdGeom.Points(stage.GetPrimAtPath(f"/Twin/E1_scan/{part}")).GetPointsAttr().Get())
             for part in PARTS]
    assert sizes == [64, 64, 64, 8]
    # a plain USD reader places the parts by the set's transform: world points equal the written ones
    world = np.concatenate([
        np.asarray(UsdGeom.Points(prim).GetPointsAttr().Get(), dtype=np.float64)
        + np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(0).ExtractTranslation())
        for prim in (stage.GetPrimAtPath(f"/Twin/E1_scan/{part}") for part in PARTS)])
    assert np.allclose(world, epochs["E1"][1].points, rtol=0, atol=1e-4)


def test_a_later_epoch_restates_only_the_parts_that_changed(big_twin: tuple[Path, dict]) -> None:
    twin, epochs = big_twin
    state = np.array(epochs["E2"][1].state)
    state[70:75] = 2  # rows of the second part only
    store = TwinStore.open(twin)
    store.write_epoch("E3", [mesh_set(), points_set(state=state, visible=np.arange(200) >= 20)], {"epoch": "E3"})
    layer = Sdf.Layer.FindOrOpen(str(twin / "epochs" / "E3.usdc"))
    restated = {part: bool(layer.GetPrimAtPath(Sdf.Path(f"/Twin/E1_scan/{part}"))
                           and layer.GetPrimAtPath(Sdf.Path(f"/Twin/E1_scan/{part}")).attributes) for part in PARTS}
    assert restated == {"part_0000": False, "part_0001": True, "part_0002": False, "part_0003": False}
    back = next(es for es in store.read_epoch("E3") if es.key == "E1_scan")
    assert np.array_equal(back.state, state) and np.array_equal(back.visible, np.arange(200) >= 20)
    with pytest.raises(TwinStoreError, match="geometry of an existing element set cannot change: E1_scan"):
        store.write_epoch("E4", [mesh_set(), dataclasses.replace(points_set(), points=points_set().points + 0.5)],
                          {"epoch": "E4"})


def test_a_set_hidden_whole_hides_its_parts_and_is_retired(big_twin: tuple[Path, dict]) -> None:
    twin, _ = big_twin
    store = TwinStore.open(twin)
    store.write_epoch("E3", [mesh_set(), points_set(state=np.full(200, 2, np.uint8), visible=np.zeros(200, bool))],
                      {"epoch": "E3"})
    stage = Usd.Stage.Open(str(twin / "twin.usda"))
    for part in PARTS:
        assert UsdGeom.Imageable(stage.GetPrimAtPath(f"/Twin/E1_scan/{part}")).ComputeVisibility() == "invisible"
    assert store.retired_removed("E3") == {"E1_scan": 200}
    store.write_epoch("E4", [mesh_set()], {"epoch": "E4"})  # a retired set may be left out
    assert np.array_equal(next(es for es in store.read_epoch("E4") if es.key == "E1_scan").state, np.full(200, 2))


def test_a_set_written_in_one_payload_layer_before_parts_still_reads_and_takes_epochs(tmp_path: Path) -> None:
    store = TwinStore.create(tmp_path / "twin")
    store.write_epoch("E0", [mesh_set()], {"epoch": "E0"})
    store.write_epoch("E1", [mesh_set(), points_set()], {"epoch": "E1"})
    # rewrite E1 as gdt wrote large sets before parts: the whole set in one payload layer, one arc on /Twin/<key>
    old = Sdf.Layer.CreateAnonymous(".usdc")
    define_element_set(Usd.Stage.Open(old), points_set())
    old.Export(str(tmp_path / "twin" / "epochs" / "E1.E1_scan.usdc"))
    layer = Sdf.Layer.FindOrOpen(str(tmp_path / "twin" / "epochs" / "E1.usdc"))
    scan = layer.GetPrimAtPath(Sdf.Path("/Twin/E1_scan"))
    scan.specifier = Sdf.SpecifierDef
    scan.payloadList.prependedItems = [Sdf.Payload("./E1.E1_scan.usdc", Sdf.Path("/Twin/E1_scan"))]
    layer.Save()
    _drop_recorded_digests(tmp_path / "twin", "E1")
    store = TwinStore.open(tmp_path / "twin")
    assert not parts.is_parted(Usd.Stage.Open(str(tmp_path / "twin" / "twin.usda")).GetPrimAtPath("/Twin/E1_scan"))
    state = np.ones(200, np.uint8)
    state[:10] = 2
    store.write_epoch("E2", [mesh_set(), points_set(state=state)], {"epoch": "E2"})
    back = next(es for es in store.read_epoch("E2") if es.key == "E1_scan")
    assert np.array_equal(back.state, state)
    assert np.allclose(back.points, points_set().points, rtol=0, atol=1e-4)


def _drop_recorded_digests(twin: Path, epoch_id: str) -> None:
    """Forget the sha256s of an epoch's files (as a twin written before they were recorded)."""
    root = Sdf.Layer.FindOrOpen(str(twin / "twin.usda"))
    data = dict(root.customLayerData)
    gdt = dict(data["gdt"])
    gdt["layer_sha256"] = {k: v for k, v in dict(gdt["layer_sha256"]).items() if f"/{epoch_id}." not in k}
    root.customLayerData = {**data, "gdt": gdt}
    root.Save()


def test_a_viewer_opening_unloaded_sees_only_the_preview(big_twin: tuple[Path, dict]) -> None:
    twin, _ = big_twin
    stage = Usd.Stage.Open(str(twin / "twin.usda"), Usd.Stage.LoadNone)
    scan = stage.GetPrimAtPath("/Twin/E1_scan")
    assert scan and parts.is_parted(scan)
    for part in PARTS:
        prim = stage.GetPrimAtPath(f"/Twin/E1_scan/{part}")
        assert prim and not prim.IsLoaded() and not UsdGeom.Points(prim).GetPointsAttr().HasValue()
    preview = UsdGeom.Points(stage.GetPrimAtPath("/Previews/E1_scan"))
    assert len(preview.GetPointsAttr().Get()) == 50
    colours = np.asarray(preview.GetDisplayColorPrimvar().Get())
    # E2's states on every 4th point: the first ten sampled were marked new, the rest unchanged
    assert np.allclose(colours[:10], STATE_COLORS[1]) and np.allclose(colours[10:], STATE_COLORS[0])
    widths = np.asarray(preview.GetWidthsAttr().Get())
    assert np.all(widths[:5] == 0) and np.all(widths[5:] > 0)  # the first 20 points are hidden in E2
    stage.Load("/Twin/E1_scan/part_0002")  # one part on demand: only its rows
    assert stage.GetPrimAtPath("/Twin/E1_scan/part_0002").IsLoaded()
    assert not stage.GetPrimAtPath("/Twin/E1_scan/part_0001").IsLoaded()
    assert len(UsdGeom.Points(stage.GetPrimAtPath("/Twin/E1_scan/part_0002")).GetPointsAttr().Get()) == 64
    stage.Load("/Twin/E1_scan")
    assert sum(len(UsdGeom.Points(stage.GetPrimAtPath(f"/Twin/E1_scan/{part}")).GetPointsAttr().Get())
               for part in PARTS) == 200


def test_a_corrupted_payload_is_named(big_twin: tuple[Path, dict]) -> None:
    twin, _ = big_twin
    path = twin / "epochs" / "E1.E1_scan.part_0001.usdc"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(TwinStoreError, match=r"E1\.E1_scan\.part_0001\.usdc of epoch E1 is corrupted"):
        TwinStore.open(twin).read_epoch("E2")


def test_the_twin_moves_with_its_payloads(big_twin: tuple[Path, dict], tmp_path: Path) -> None:
    twin, _ = big_twin
    moved = tmp_path / "elsewhere" / "twin"
    shutil.copytree(twin, moved)
    shutil.rmtree(twin)
    store = TwinStore.open(moved)
    store.verify()
    assert len(next(es for es in store.read_epoch("E2") if es.key == "E1_scan").points) == 200
    flat = store.flatten("E2", tmp_path / "flat.usdc")
    flat_stage = Usd.Stage.Open(str(flat))
    assert sum(len(UsdGeom.Points(flat_stage.GetPrimAtPath(f"/Twin/E1_scan/{part}")).GetPointsAttr().Get())
               for part in PARTS) == 200


def test_writing_a_large_set_holds_one_part_at_a_time(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(payloads, "PAYLOAD_ELEMENTS", 100)
    monkeypatch.setattr(parts, "PART_ELEMENTS", 64)
    alive: list[int] = []
    define = payloads.define_element_set

    def counting(stage: Usd.Stage, es: ElementSet, *args: object) -> None:
        # the in-memory layers holding a part's arrays still alive when the next part is built (the epoch layer
        # holds the parts' payload arcs, without attributes)
        alive.append(sum(1 for layer in Sdf.Layer.GetLoadedLayers()
                         if layer.anonymous and any(spec.name.startswith("part_") and "points" in spec.attributes
                                                    for prim in layer.rootPrims for child in prim.nameChildren
                                                    for spec in child.nameChildren)))
        define(stage, es, *args)

    monkeypatch.setattr(payloads, "define_element_set", counting)
    store = TwinStore.create(tmp_path / "twin")
    store.write_epoch("E0", [points_set()], {"epoch": "E0"})
    assert alive == [0, 0, 0, 0]


def _rows_on_demand(es: ElementSet, asked: list[tuple[int, int]]) -> RowsOnDemand:
    """``es`` as the engine hands a point set to the writer: rows made on request, each request recorded."""
    def make(start: int, stop: int) -> ElementSet:
        asked.append((start, stop))
        rows = {name: np.asarray(getattr(es, name))[start:stop] for name in parts.PER_ELEMENT
                if getattr(es, name) is not None}
        return dataclasses.replace(es, **rows)

    return RowsOnDemand(key=es.key, points=es.points, state=es.state, visible=es.visible, identity=es.identity,
                        item=es.item, make=make)


def _files(twin: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((twin / "epochs").iterdir())}


def test_a_set_made_part_by_part_writes_the_twin_the_whole_set_writes(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(payloads, "PAYLOAD_ELEMENTS", 100)
    monkeypatch.setattr(parts, "PART_ELEMENTS", 64)
    state = np.zeros(200, np.uint8)
    state[130:140] = 2
    epochs = {"E0": [points_set()], "E1": [points_set(state=state, visible=np.arange(200) < 190)]}
    asked: list[tuple[int, int]] = []
    for name, source in (("whole", lambda es: es), ("rows", lambda es: _rows_on_demand(es, asked))):
        store = TwinStore.create(tmp_path / name)
        for eid, sets in epochs.items():
            store.write_epoch(eid, [source(es) for es in sets], {"epoch": eid})
    # the writer asked for one part's rows at a time, never the whole set: four parts written, four compared
    assert asked == [(0, 64), (64, 128), (128, 192), (192, 200)] * 2
    assert _files(tmp_path / "rows") == _files(tmp_path / "whole")
    # a set small enough for one prim is made whole, once
    monkeypatch.setattr(payloads, "PAYLOAD_ELEMENTS", 1000)
    asked.clear()
    TwinStore.create(tmp_path / "small").write_epoch("E0", [_rows_on_demand(points_set(), asked)], {})
    assert asked == [(0, 200)]
