"""Readers are their own extension kind (the ``gdt_readers`` hook), and a hook implementation that matches no hook
is an error naming its plugin."""

from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import pytest
from pydantic import BaseModel

from gdt_pipeline import Dataset, PluginError, ReaderSpec, ReadRequest, hookimpl
from gdt_pipeline.plugins import load_registry
from gdt_pipeline.runner import run_workflow
from twin_store import TwinStore

from .conftest import make_cube_scene, write_cube_workflow


class CsvParams(BaseModel):
    """Parameters of the test's CSV reader."""

    delimiter: str = ","


def _read_csv(req: ReadRequest) -> Dataset:
    pts = np.loadtxt(req.path, delimiter=req.params.delimiter, ndmin=2)
    return Dataset(name=req.name, role=req.role, points=pts)


def _plugin(name: str, **hooks) -> types.ModuleType:
    mod = types.ModuleType(name)
    for hook, fn in hooks.items():
        setattr(mod, hook, hookimpl(fn))
    return mod


def _csv_plugin() -> types.ModuleType:
    return _plugin("csv_reader", gdt_readers=lambda: [
        ReaderSpec(name="csv_points", version="1.0", extensions=(".csv",), read=_read_csv, params=CsvParams)])


def test_a_third_party_reader_reads_a_workflow_input(tmp_path: Path) -> None:
    scene = make_cube_scene(tmp_path / "scene", n_cube=600, n_new=200)
    import open3d as o3d

    pts = np.asarray(o3d.io.read_point_cloud(str(scene.scan)).points)
    csv = scene.dir / "scan.csv"
    np.savetxt(csv, pts, delimiter=",")
    scene.scan = csv
    registry = load_registry(extra=[("csv_reader", _csv_plugin())])
    assert registry.reader("csv_points").plugin == "csv_reader"
    assert [r.name for r in registry.readers_for(csv, None)] == ["csv_points"]
    result = run_workflow(write_cube_workflow(scene, tau=10.0), registry=registry)
    prov = TwinStore.open(result.twin).provenance("E1")
    assert prov["inputs"][0]["reader"] == "csv_points" and prov["inputs"][0]["elements"] == 800
    counts = result.epochs[-1].counts
    # keep_unchanged: the cube's 12 CAD facets stay; the 200 points of the new box come in, and only they
    assert counts["unchanged"] == 12 and 190 <= counts["new"] <= 210


def test_a_misspelt_hook_is_an_error_naming_the_plugin() -> None:
    typo = _plugin("typo_plugin", gdt_stage=lambda: [])
    with pytest.raises(PluginError, match=r"typo_plugin.*gdt_stage.*gdt_readers, gdt_stages"):
        load_registry(extra=[("typo_plugin", typo)])


def test_a_reader_without_extensions_is_skipped_with_a_warning() -> None:
    bad = _plugin("bad_reader", gdt_readers=lambda: [
        ReaderSpec(name="nothing", version="1", extensions=(), read=_read_csv)])
    registry = load_registry(extra=[("bad_reader", bad)])
    assert "nothing" not in registry.names("reader")
    assert any("reader 'nothing' declares no file extensions" in w for w in registry.warnings)


def test_a_name_cannot_be_both_a_stage_and_a_reader(registry) -> None:
    clash = _plugin("clash_reader", gdt_readers=lambda: [
        ReaderSpec(name="fixed", version="1", extensions=(".zzz",), read=_read_csv)])
    with pytest.raises(PluginError, match="'fixed' is both a stage"):
        load_registry(extra=[("clash_reader", clash)])


def test_what_a_reader_dropped_is_in_the_epochs_provenance(tmp_path: Path, registry) -> None:
    scene = make_cube_scene(tmp_path / "scene", n_cube=600, n_new=200)
    text = scene.cad.read_text()
    n_vertices = sum(1 for line in text.splitlines() if line.startswith("v "))
    # two zero-area facets: a repeated vertex, and three collinear vertices added for it
    extra = "v 0 0 0\nv 0.5 0 0\nv 1 0 0\n"
    degenerate = f"f 1 1 2\nf {n_vertices + 1} {n_vertices + 2} {n_vertices + 3}\n"
    scene.cad.write_text(text + extra + degenerate)
    result = run_workflow(write_cube_workflow(scene, tau=10.0), registry=registry)
    cad_input = TwinStore.open(result.twin).provenance("E0")["inputs"][0]
    assert cad_input["notes"] == {"degenerate_facets_dropped": 2} and cad_input["elements"] == 12
