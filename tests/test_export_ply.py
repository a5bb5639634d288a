"""`gdt export --format ply`: binary PLY files that plyfile reads back with every per-element value of the twin (per
point for point sets, per facet for meshes), and `--scope epoch` (ply, las): only the visible elements the epoch
itself supplied."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
from plyfile import PlyData

from gdt_pipeline.runner import run_workflow
from twin_store import STATE_COLORS, ElementSet, TwinStore

from .conftest import make_cube_scene, run_gdt, write_cube_workflow

# the LAS extra dimensions, with the same names and types
VALUE_TYPES = {"change_state": "u1", "change_score": "f4", "p_value": "f4", "uncertainty": "f4", "source_epoch": "i4",
               "fusion_reason": "u1", "fusion_ratio": "f4"}
COLOUR_TYPES = {"red": "u1", "green": "u1", "blue": "u1"}


def cube_twin(tmp_path: Path, registry: object, *, rescan: bool = False) -> Path:
    """The cube workflow's twin (E0 the CAD, E1 the scan), with ``rescan`` a third epoch scanning the scene again."""
    workflow = write_cube_workflow(make_cube_scene(tmp_path / "cube"))
    if rescan:
        e2 = "  - id: E2\n    role: as-is\n    inputs: [{path: scan.ply, name: again}]\n"
        workflow.write_text(workflow.read_text().replace("stages:\n", e2 + "stages:\n"))
    return run_workflow(workflow, registry=registry, twin=tmp_path / "twin").twin


def check_values(data: np.ndarray, es: ElementSet, vis: np.ndarray) -> None:
    """The record array read from a PLY holds the colour and every value of the visible elements of ``es``."""
    assert np.array_equal(data["change_state"], es.state[vis])
    assert np.array_equal(data["change_score"], np.asarray(es.score, np.float32)[vis], equal_nan=True)
    assert np.array_equal(data["uncertainty"], np.asarray(es.uncertainty_summary, np.float32)[vis])
    assert np.array_equal(data["source_epoch"], es.source_epoch[vis])
    assert np.array_equal(data["fusion_reason"], es.reason[vis])
    assert np.array_equal(data["fusion_ratio"], np.asarray(es.reason_ratio, np.float32)[vis], equal_nan=True)
    if es.p_value is None:
        assert np.all(np.isnan(data["p_value"]))
    else:
        assert np.array_equal(data["p_value"], np.asarray(es.p_value, np.float32)[vis], equal_nan=True)
    colour = np.round(STATE_COLORS[es.state[vis]] * 255).astype(np.uint8)
    assert np.array_equal(np.column_stack([data["red"], data["green"], data["blue"]]), colour)


def test_ply_export_carries_every_value_of_the_twin(tmp_path: Path, registry: object) -> None:
    twin = cube_twin(tmp_path, registry)
    res = run_gdt("export", str(twin), "--format", "ply", "-o", str(tmp_path / "out"))
    assert res.returncode == 0, res.stderr
    sets = {es.key: es for es in TwinStore.open(twin).read_epoch("E1")}
    files = sorted((tmp_path / "out").glob("*.ply"))
    assert [f.stem for f in files] == sorted(k for k, es in sets.items() if es.visible.any())
    assert {sets[f.stem].kind for f in files} == {"mesh", "points"}  # the CAD and the scan
    for path in files:
        es, ply = sets[path.stem], PlyData.read(str(path))
        vis = np.asarray(es.visible, dtype=bool)
        assert not ply.text and ply.byte_order == "<"
        assert "units: m (1 unit = 1 m)" in ply.comments
        assert all(any(c.startswith(f"{name}: ") for c in ply.comments) for name in VALUE_TYPES)
        vertex = ply["vertex"]
        xyz = np.column_stack([vertex["x"], vertex["y"], vertex["z"]])
        if es.kind == "mesh":
            face = ply["face"]
            assert {p.name: p.val_dtype for p in vertex.properties} == {"x": "f8", "y": "f8", "z": "f8"}
            assert np.array_equal(xyz, es.points)  # every vertex, so the indices stay the twin's
            indices = face.ply_property("vertex_indices")
            assert (indices.len_dtype, indices.val_dtype) == ("u1", "i4")
            assert {p.name: p.val_dtype for p in face.properties[1:]} == {**COLOUR_TYPES, **VALUE_TYPES}
            assert len(face.data) == int(vis.sum()) == 12
            assert np.array_equal(np.stack(face["vertex_indices"]), es.faces[vis])
            check_values(face.data, es, vis)
        else:
            assert {p.name: p.val_dtype for p in vertex.properties} == {"x": "f8", "y": "f8", "z": "f8",
                                                                        **COLOUR_TYPES, **VALUE_TYPES}
            assert len(vertex.data) == int(vis.sum()) > 900
            assert np.array_equal(xyz, es.points[vis])
            check_values(vertex.data, es, vis)


def read_values(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(change_state, source_epoch) per element of an exported PLY (faces of a mesh) or LAS file."""
    if path.suffix == ".las":
        las = laspy.read(str(path))
        return np.asarray(las.change_state), np.asarray(las.source_epoch)
    ply = PlyData.read(str(path))
    data = ply["face"].data if "face" in ply else ply["vertex"].data
    return data["change_state"], data["source_epoch"]


@pytest.mark.parametrize("fmt", ["ply", "las"])
def test_scope_epoch_keeps_only_what_the_epoch_supplied(tmp_path: Path, registry: object, fmt: str) -> None:
    twin = cube_twin(tmp_path, registry, rescan=True)
    store = TwinStore.open(twin)
    epochs = store.epochs()
    assert epochs == ["E0", "E1", "E2"]
    for index, epoch in enumerate(epochs):
        res = run_gdt("export", str(twin), "--epoch", epoch, "--format", fmt, "--scope", "epoch",
                      "-o", str(tmp_path / f"{fmt}_{epoch}"))
        assert res.returncode == 0, res.stderr
        sets = {es.key: es for es in store.read_epoch(epoch) if fmt == "ply" or es.kind == "points"}
        supplied = {k: es.visible.astype(bool) & (es.source_epoch == index) for k, es in sets.items()}
        files = sorted((tmp_path / f"{fmt}_{epoch}").glob(f"*.{fmt}"))
        assert [f.stem for f in files] == sorted(k for k, mask in supplied.items() if mask.any())
        for path in files:
            state, source = read_values(path)
            assert np.array_equal(state, sets[path.stem].state[supplied[path.stem]])
            assert np.all(source == index)
    # E2 repeats E1's scan, so none of it comes in: its composite is all earlier data and the epoch scope is empty
    assert not files
    res = run_gdt("export", str(twin), "--format", fmt, "--scope", "composite", "-o", str(tmp_path / f"{fmt}_all"))
    assert res.returncode == 0, res.stderr
    composite = sorted(f.stem for f in (tmp_path / f"{fmt}_all").glob(f"*.{fmt}"))
    assert composite == (["E0_cad", "E1_scan"] if fmt == "ply" else ["E1_scan"])


def test_scope_is_refused_for_other_formats(tmp_path: Path, registry: object) -> None:
    twin = cube_twin(tmp_path, registry)
    res = run_gdt("export", str(twin), "--format", "usda", "--scope", "epoch", "-o", str(tmp_path / "t.usda"))
    assert res.returncode == 2, res.stderr
    assert "--scope" in res.stderr and "usda" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "t.usda").exists()
