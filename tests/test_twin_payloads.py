"""Large point sets in payload layers: read back whole and exact, loaded on demand by a viewer that opens the twin
unloaded (it then sees only the decimated preview), overridden by later epochs, checked against their sha256, and
movable with the twin."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom

import twin_store.payloads as payloads
from twin_store import STATE_COLORS, TwinStore, TwinStoreError

from .test_twin_store import mesh_set, points_set


@pytest.fixture
def big_twin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, dict]:
    # 200 points count as "large" here, and the preview keeps every 4th of them
    monkeypatch.setattr(payloads, "PAYLOAD_ELEMENTS", 100)
    monkeypatch.setattr(payloads, "PREVIEW_POINTS", 50)
    store = TwinStore.create(tmp_path / "twin")
    state = np.zeros(200, np.uint8)
    state[:40] = 1
    epochs = {"E0": [mesh_set()], "E1": [mesh_set(), points_set()], "E2": [mesh_set(), points_set(state=state,
                                                                                   visible=np.arange(200) >= 20)]}
    for eid, sets in epochs.items():
        store.write_epoch(eid, sets, {"epoch": eid})
    return tmp_path / "twin", epochs


def test_a_large_set_lives_in_its_own_layer_and_reads_back_exactly(big_twin: tuple[Path, dict]) -> None:
    twin, epochs = big_twin
    assert sorted(p.name for p in (twin / "epochs").iterdir()) == ["E0.usdc", "E1.E1_scan.usdc", "E1.usdc",
                                                                      "E2.usdc"]
    store = TwinStore.open(twin)
    for eid, written in epochs.items():
        got = {es.key: es for es in store.read_epoch(eid)}
        for es in written:
            back = got[es.key]
            assert np.allclose(back.points, es.points, rtol=0, atol=1e-4)
            assert np.array_equal(back.state, es.state) and np.array_equal(back.visible, es.visible)
            assert np.allclose(back.score, es.score, equal_nan=True)
    # the epoch layer holds an arc, not the points
    layer = Sdf.Layer.FindOrOpen(str(twin / "epochs" / "E1.usdc"))
    spec = layer.GetPrimAtPath(Sdf.Path("/Twin/E1_scan"))
    assert [p.assetPath for p in spec.payloadList.prependedItems] == ["./E1.E1_scan.usdc"]
    assert "points" not in spec.attributes


def test_a_viewer_opening_unloaded_sees_only_the_preview(big_twin: tuple[Path, dict]) -> None:
    twin, _ = big_twin
    stage = Usd.Stage.Open(str(twin / "twin.usda"), Usd.Stage.LoadNone)
    scan = stage.GetPrimAtPath("/Twin/E1_scan")
    assert scan and not scan.IsLoaded() and not UsdGeom.Points(scan).GetPointsAttr().HasValue()
    preview = UsdGeom.Points(stage.GetPrimAtPath("/Previews/E1_scan"))
    assert len(preview.GetPointsAttr().Get()) == 50
    colours = np.asarray(preview.GetDisplayColorPrimvar().Get())
    # E2's states on every 4th point: the first ten sampled were marked new, the rest unchanged
    assert np.allclose(colours[:10], STATE_COLORS[1]) and np.allclose(colours[10:], STATE_COLORS[0])
    widths = np.asarray(preview.GetWidthsAttr().Get())
    assert np.all(widths[:5] == 0) and np.all(widths[5:] > 0)  # the first 20 points are hidden in E2
    stage.Load("/Twin/E1_scan")
    assert len(UsdGeom.Points(stage.GetPrimAtPath("/Twin/E1_scan")).GetPointsAttr().Get()) == 200


def test_a_corrupted_payload_is_named(big_twin: tuple[Path, dict]) -> None:
    twin, _ = big_twin
    path = twin / "epochs" / "E1.E1_scan.usdc"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(TwinStoreError, match=r"E1\.E1_scan\.usdc of epoch E1 is corrupted"):
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
    assert len(UsdGeom.Points(Usd.Stage.Open(str(flat)).GetPrimAtPath("/Twin/E1_scan")).GetPointsAttr().Get()) == 200
