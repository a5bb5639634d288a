"""Plugin discovery through entry points: built-ins and the sample plugin alike; duplicates, broken and blocked
plugins; the engine never imports a concrete stage."""

from __future__ import annotations

import importlib.metadata as im
import json
import re
import sys
import types
from pathlib import Path

import pytest
from pydantic import BaseModel

from gdt_pipeline import PluginError, StageSpec, hookimpl
from gdt_pipeline.plugins import FAMILIES, load_registry
from gdt_pipeline.plugins import registry as plugins_mod

from .conftest import REPO, run_gdt

BUILTIN_ENTRY_POINTS = {"io", "registration", "uncertainty", "correspondence", "distance", "threshold", "fusion"}


def test_builtins_come_through_entry_points(registry) -> None:
    eps = {ep.name: ep for ep in im.entry_points(group="gdt_pipeline")}
    assert set(eps) >= BUILTIN_ENTRY_POINTS
    for name in ("identity", "constant", "nearest", "bhattacharyya", "fixed", "keep_unchanged"):
        spec = registry.get(name)
        assert spec.plugin == "gdt-pipeline" and spec.entry_point in BUILTIN_ENTRY_POINTS
        assert issubclass(spec.params, BaseModel) and spec.family in FAMILIES and spec.version
    for name in ("trimesh_mesh", "open3d_points", "laspy_points"):  # readers: their own hook, same entry points
        reader = registry.reader(name)
        assert reader.plugin == "gdt-pipeline" and reader.entry_point == "io" and reader.extensions


def test_sample_plugin_is_discovered_through_its_entry_point(registry) -> None:
    ep = next(ep for ep in im.entry_points(group="gdt_pipeline") if ep.name == "c2c")
    assert ep.dist is not None and ep.dist.name == "gdt-c2c" and ep.value == "gdt_c2c"
    spec = registry.get("c2c")
    assert (spec.family, spec.plugin, spec.entry_point) == ("distance", "gdt-c2c", "c2c")
    res = run_gdt("plugins", "--json")
    assert res.returncode == 0, res.stderr
    rows = {r["name"]: r for r in json.loads(res.stdout)}
    assert rows["c2c"]["plugin"] == "gdt-c2c" and rows["c2c"]["family"] == "distance"
    assert rows["bhattacharyya"]["plugin"] == "gdt-pipeline"
    assert rows["bhattacharyya"]["tiling"] == "tile" and rows["calibrated_threshold"]["tiling"] == "epoch"
    assert {r["name"] for r in rows.values() if r["family"] == "executor"} == {"serial", "processes", "dask"}
    table = run_gdt("plugins")
    assert re.search(r"distance\s+│\s+c2c\s+│\s+gdt-c2c", table.stdout), table.stdout


def test_blocking_a_plugin_by_environment(registry) -> None:
    res = run_gdt("plugins", "--json", env={"GDT_BLOCKED_PLUGINS": "c2c, correspondence"})
    names = {r["name"] for r in json.loads(res.stdout)}
    assert "c2c" not in names and "nearest" not in names and "bhattacharyya" in names
    blocked = load_registry(blocked={"gdt-c2c"})
    assert "c2c" not in blocked and "fixed" in blocked


class _P(BaseModel):
    tau: float = 1.0


def _module(name: str, specs: list[StageSpec] | Exception) -> types.ModuleType:
    mod = types.ModuleType(name)

    @hookimpl
    def gdt_stages() -> list[StageSpec]:
        if isinstance(specs, Exception):
            raise specs
        return specs

    mod.gdt_stages = gdt_stages
    return mod


def _run(ctx):
    return {}


def test_duplicate_stage_names_are_rejected_naming_both() -> None:
    dup = _module("dup", [StageSpec(name="fixed", family="threshold", version="9", params=_P, run=_run)])
    with pytest.raises(PluginError) as info:
        load_registry(blocked=(), extra=[("dup", dup)])
    msg = str(info.value)
    assert "'fixed' is provided twice" in msg and "'threshold'" in msg and "'dup'" in msg
    assert "GDT_BLOCKED_PLUGINS" in msg


def test_broken_plugins_are_warnings_not_crashes(monkeypatch) -> None:
    real = list(im.entry_points(group="gdt_pipeline"))
    broken_ep = im.EntryPoint(name="broken", value="no_such_module_for_gdt", group="gdt_pipeline")
    monkeypatch.setattr(plugins_mod, "_entry_points", lambda: [*real, broken_ep])
    raising = _module("raising", RuntimeError("boom"))
    malformed = _module("malformed", [StageSpec(name="Bad Name", family="distance", version="1", params=_P,
                                                run=_run)])
    reg = load_registry(blocked=(), extra=[("raising", raising), ("malformed", malformed)])
    joined = "\n".join(reg.warnings)
    assert "plugin 'broken'" in joined and "ModuleNotFoundError" in joined
    assert "gdt_stages() raised RuntimeError: boom" in joined
    assert "stage name 'Bad Name' must match" in joined
    assert "bhattacharyya" in reg  # the rest still works


def test_params_models_are_made_strict() -> None:
    mod = _module("lenient", [StageSpec(name="lenient", family="threshold", version="1", params=_P, run=_run,
                                        requires=("scores",), provides=("change",))])
    reg = load_registry(blocked=(), extra=[("lenient", mod)])
    params = reg.get("lenient").params
    with pytest.raises(Exception, match="Extra inputs are not permitted"):
        params(tau=1.0, tua=2.0)


def test_unknown_stage_name_lists_the_choices(registry) -> None:
    with pytest.raises(PluginError) as info:
        registry.get("bhatacharyya")
    assert "did you mean 'bhattacharyya'" in str(info.value) and "choose one of:" in str(info.value)


def test_engine_never_imports_a_concrete_stage() -> None:
    bad = []
    for path in (REPO / "gdt_pipeline").rglob("*.py"):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if re.match(r"^\s*(from|import)\s+(stages|plugins|gdt_c2c)\b", line):
                bad.append(f"{path}:{n}: {line.strip()}")
    for path in (REPO / "twin_store").rglob("*.py"):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if re.match(r"^\s*(from|import)\s+(stages|plugins|gdt_pipeline|open3d|trimesh|scipy)\b", line):
                bad.append(f"{path}:{n}: {line.strip()}")
    assert not bad, bad
    assert Path(REPO / "plugins" / "gdt-c2c" / "pyproject.toml").is_file()


def test_same_entry_point_name_from_another_distribution_is_not_skipped(monkeypatch) -> None:
    """A third party's entry point called `io` must still load (and here clash on its stage name, loudly)."""
    third = _module("third_party_io", [StageSpec(name="fixed", family="threshold", version="2", params=_P, run=_run)])
    monkeypatch.setitem(sys.modules, "third_party_io", third)
    real = list(im.entry_points(group="gdt_pipeline"))
    clash = im.EntryPoint(name="io", value="third_party_io", group="gdt_pipeline")
    monkeypatch.setattr(plugins_mod, "_entry_points", lambda: [*real, clash])
    with pytest.raises(PluginError, match="stage name 'fixed' is provided twice"):
        load_registry(blocked=())
