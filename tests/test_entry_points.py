"""The two extension points of docs/engine.md, installed as a third party installs them: the distance measure and the
region-of-view builder of its examples become modules of a distribution whose entry points are the doc's own lines
(a ``.dist-info`` on ``PYTHONPATH``, nothing registered by hand), and ``gdt run`` uses both, whole and in tiles."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from .conftest import REPO, CubeScene, run_gdt, write_cube_workflow

DOC = REPO / "docs" / "engine.md"
SECTIONS = ("Adding a distance measure", "Adding a region-of-view builder")


def _section(title: str) -> str:
    text = DOC.read_text(encoding="utf-8")
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end if end >= 0 else None]


def _install(site: Path) -> dict[str, str]:
    """Each section's one Python block as a module under the name its one entry-point line gives, and a
    distribution's metadata listing those entry points."""
    site.mkdir()
    entry_points = {}
    for title in SECTIONS:
        section = _section(title)
        [code] = re.findall(r"```python\n(.*?)```", section, flags=re.S)
        [toml] = re.findall(r"```toml\n(.*?)```", section, flags=re.S)
        [(name, target)] = tomllib.loads(toml)["project"]["entry-points"]["gdt_pipeline"].items()
        (site / f"{target}.py").write_text(code, encoding="utf-8")
        entry_points[name] = target
    dist = site / "gdt_doc_examples-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: gdt-doc-examples\nVersion: 1.0\n")
    lines = "".join(f"{name} = {target}\n" for name, target in entry_points.items())
    (dist / "entry_points.txt").write_text(f"[gdt_pipeline]\n{lines}")
    return entry_points


def _workflow(scene: CubeScene, twin: str) -> Path:
    """The cube workflow scored by the doc's measure, with the doc's region of view from a station beside the cube."""
    wf = write_cube_workflow(scene, twin=twin, distance="mahalanobis", tau=4.0, name=f"{twin}.yaml")
    text = wf.read_text()
    text = text.replace("{path: scan.ply, name: scan}", "{path: scan.ply, name: scan, viewpoints: [[2.6, 0.0, 0.5]]}")
    text = text.replace("  - uses: nearest\n    role: as-is\n",
                        "  - uses: nearest\n    role: as-is\n    with: {max_distance: 0.1}\n")
    # the cube scan samples every face alike, as no station sees it: sight by the station's rays, not its depth image
    sphere = "  - uses: station_sphere\n    role: as-is\n    with: {radius: 2.4, sight: stations, occlusion: false}\n"
    text = text.replace("  - uses: keep_unchanged\n", sphere + "  - uses: keep_unchanged\n")
    wf.write_text(text)
    return wf


def _layer(twin: Path) -> tuple[dict[str, dict[str, np.ndarray]], dict]:
    from pxr import Sdf, Usd, UsdGeom

    stage = Usd.Stage.Open(str(twin / "twin.usda"))
    values = {}
    for prim in stage.Traverse():
        pv = UsdGeom.PrimvarsAPI(prim)
        if pv.HasPrimvar("gdt:changeState"):
            values[prim.GetName()] = {n: np.asarray(pv.GetPrimvar(f"gdt:{n}").Get())
                                      for n in ("changeState", "changeScore", "visible")}
    layer = Sdf.Layer.FindOrOpen(str(twin / "epochs" / "E1.usdc"))
    return values, json.loads(layer.customLayerData["gdt"]["provenance_json"])


def test_a_plugins_measure_and_region_builder_run_through_entry_points_whole_and_in_tiles(
        cube_scene: CubeScene, tmp_path: Path) -> None:
    site = tmp_path / "site"
    assert _install(site) == {"my_measures": "my_measures", "my_regions": "my_regions"}
    env = {"PYTHONPATH": str(site)}
    listed = run_gdt("plugins", "--json", env=env)
    assert listed.returncode == 0, listed.stderr
    by_name = {row["name"]: row for row in json.loads(listed.stdout)}
    for name, family, entry_point in (("mahalanobis", "distance", "my_measures"),
                                      ("station_sphere", "rov", "my_regions")):
        assert by_name[name]["family"] == family and by_name[name]["plugin"] == "gdt-doc-examples"
        assert entry_point in by_name[name]["entry_point"]

    whole = run_gdt("run", str(_workflow(cube_scene, "whole")), "-q", "--no-report", env=env)
    assert whole.returncode == 0, whole.stderr
    tiled = run_gdt("run", str(_workflow(cube_scene, "tiled")), "--tile", "0.5", "-q", "--no-report", env=env)
    assert tiled.returncode == 0, tiled.stderr
    (values, prov), (tiled_values, tiled_prov) = (_layer(cube_scene.dir / t) for t in ("whole", "tiled"))

    stages = {st["uses"]: st for st in tiled_prov["stages"]}
    assert stages["mahalanobis"]["plugin"] == "gdt-doc-examples"
    assert stages["mahalanobis"]["report"]["tiling"]["tiles"] > 1  # the measure ran tile by tile
    assert "tiling" not in stages["station_sphere"]["report"]  # a region of view sees the whole epoch
    assert "sphere of radius 2.4" in stages["station_sphere"]["report"]["region_of_view"]["parts"][0]
    assert values.keys() == tiled_values.keys()
    for key in values:  # the tiled twin is the whole run's, element by element
        for name in ("changeState", "changeScore", "visible"):
            np.testing.assert_array_equal(values[key][name], tiled_values[key][name])

    scan, cad = values["E1_scan"], values["E0_cad"]
    truth = cube_scene.changed
    flagged = scan["changeState"] == 1
    assert 2 * np.sum(flagged & truth) / (flagged.sum() + truth.sum()) > 0.9  # the doc's measure finds the new box
    # the sphere of 2.4 m around a station at x = 2.6 holds the cube's near face, which faces it and is measured
    # (unchanged); the far face (x = -0.5) lies outside it and the others face away: outside the region of view
    import trimesh

    cube = trimesh.load(cube_scene.cad, process=False)
    facing = np.isclose(cube.triangles_center[:, 0], 0.5)
    np.testing.assert_array_equal(cad["changeState"], np.where(facing, 0, 3))
    assert facing.sum() == 2 and cad["visible"].all()  # nothing removed
    assert prov["stages"][-2]["uses"] == "station_sphere"


@pytest.mark.parametrize("title", SECTIONS)
def test_each_example_is_one_file_plus_one_entry_point_line(title: str) -> None:
    section = _section(title)
    assert len(re.findall(r"```python\n", section)) == 1 and len(re.findall(r"```toml\n", section)) == 1
    [code] = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    imported = re.findall(r"^(?:from|import) ([\w.]+)", code, flags=re.M)
    assert all(not part.startswith("_") for mod in imported for part in mod.split("."))  # no private module
    assert not any(mod.startswith("stages") for mod in imported)  # the public API of gdt_pipeline only
