"""The IFC reader: one mesh per product with its GlobalId and class, in world coordinates and metres; and end to end,
a wall missing from a scan of the room is reported by its GlobalId in ``gdt log``."""

from __future__ import annotations

import json
import re
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from gdt_pipeline import InputError, ReadRequest
from gdt_pipeline.audit import audit_twin
from gdt_pipeline.runner import read_datasets, run_workflow
from twin_store import TwinStore

from .conftest import run_gdt, write_points_ply

ifcopenshell = pytest.importorskip("ifcopenshell")

HEIGHT, THICK = 2.5, 0.2
# name: (length, placement origin, rotation about z); a 4 m × 3 m room, the short walls between the long ones
WALLS = {"Wall A": (4.0, (0.0, 0.0, 0.0), 0.0), "Wall C": (4.0, (0.0, 2.8, 0.0), 0.0),
         "Wall B": (2.6, (4.0, 0.2, 0.0), np.pi / 2), "Wall D": (2.6, (0.2, 0.2, 0.0), np.pi / 2)}
GONE = "Wall C"
FLOOR = "Fußboden"  # not ASCII: the twin's key must still be a USD identifier
EYE = (2.0, 1.5, 1.5)


@dataclass
class Room:
    """The IFC file and the GlobalIds of its products by name."""

    path: Path
    guids: dict[str, str]


def _place(api, model, product, origin, angle: float) -> None:
    c, s = np.cos(angle), np.sin(angle)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = origin
    api.run("geometry.edit_object_placement", model, product=product, matrix=m)


def make_room(path: Path) -> Room:
    """An IFC4 room in millimetres (the reader must hand back metres): four walls, a floor slab, and a wall with an
    axis but no body (nothing to tessellate)."""
    import ifcopenshell.api as api

    model = ifcopenshell.file(schema="IFC4")
    project = api.run("root.create_entity", model, ifc_class="IfcProject", name="Room")
    api.run("unit.assign_unit", model)  # the API's default: millimetres
    ctx = api.run("context.add_context", model, context_type="Model")
    body = api.run("context.add_context", model, context_type="Model", context_identifier="Body",
                   target_view="MODEL_VIEW", parent=ctx)
    plan = api.run("context.add_context", model, context_type="Plan")
    axis = api.run("context.add_context", model, context_type="Plan", context_identifier="Axis",
                   target_view="GRAPH_VIEW", parent=plan)
    parent = project
    for cls, name in (("IfcSite", "Site"), ("IfcBuilding", "House"), ("IfcBuildingStorey", "Ground floor")):
        child = api.run("root.create_entity", model, ifc_class=cls, name=name)
        api.run("aggregate.assign_object", model, relating_object=parent, products=[child])
        parent = child
    guids = {}
    for name, (length, origin, angle) in WALLS.items():
        wall = api.run("root.create_entity", model, ifc_class="IfcWall", name=name)
        rep = api.run("geometry.add_wall_representation", model, context=body, length=length, height=HEIGHT,
                      thickness=THICK)
        api.run("geometry.assign_representation", model, product=wall, representation=rep)
        _place(api, model, wall, origin, angle)
        guids[name] = wall.GlobalId
    slab = api.run("root.create_entity", model, ifc_class="IfcSlab", name=FLOOR)
    rep = api.run("geometry.add_slab_representation", model, context=body, depth=THICK,
                  polyline=[(0, 0), (4, 0), (4, 3), (0, 3), (0, 0)])
    api.run("geometry.assign_representation", model, product=slab, representation=rep)
    _place(api, model, slab, (0.0, 0.0, -THICK), 0.0)
    guids[FLOOR] = slab.GlobalId
    sketch = api.run("root.create_entity", model, ifc_class="IfcWall", name="Sketch")
    rep = api.run("geometry.add_axis_representation", model, context=axis, axis=[(0.0, 0.0), (1.0, 0.0)])
    api.run("geometry.assign_representation", model, product=sketch, representation=rep)
    guids["Sketch"] = sketch.GlobalId
    api.run("spatial.assign_container", model, relating_structure=parent,
            products=[p for p in model.by_type("IfcElement")])
    model.write(str(path))
    return Room(path, guids)


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Room:
    """The room, written once for the module."""
    return make_room(tmp_path_factory.mktemp("ifc") / "room.ifc")


def _area(ds) -> float:
    return float(0.5 * np.linalg.norm(ds.facet_normals(), axis=1).sum())


def test_one_dataset_per_product_with_its_identity_in_world_coordinates_and_metres(registry, room) -> None:
    parts = read_datasets(room.path, registry, name="bim", role="as-designed")
    by_name = {ds.meta["name"]: ds for ds in parts}
    assert sorted(by_name) == sorted([*WALLS, FLOOR])  # the axis-only wall has no triangles
    assert [ds.meta["global_id"] for ds in parts] == sorted(ds.meta["global_id"] for ds in parts)
    for name, (length, origin, angle) in WALLS.items():
        ds = by_name[name]
        assert ds.name == f"bim_IfcWall_{name.replace(' ', '_')}" and ds.faces is not None
        assert ds.meta == {"name": name, "global_id": room.guids[name], "ifc_class": "IfcWall",
                           "ifc_file_schema": "IFC4"}
        closed = 2 * (length * HEIGHT + length * THICK + HEIGHT * THICK)
        assert _area(ds) == pytest.approx(closed, rel=1e-6)
        # world coordinates in metres: the placement is applied and the file's millimetres converted
        lo = np.asarray(origin) - (np.array([THICK, 0, 0]) if angle else 0)
        extent = np.array([THICK, length, HEIGHT]) if angle else np.array([length, THICK, HEIGHT])
        np.testing.assert_allclose(ds.points.min(axis=0), lo, atol=1e-9)
        np.testing.assert_allclose(ds.points.max(axis=0), lo + extent, atol=1e-9)
    floor = by_name[FLOOR]
    assert floor.meta["ifc_class"] == "IfcSlab" and floor.name == "bim_IfcSlab_Fu_boden"
    assert _area(floor) == pytest.approx(2 * (4 * 3 + 4 * THICK + 3 * THICK), rel=1e-6)
    notes = parts[0].source.notes
    assert notes["products"] == 5 and notes["skipped_without_triangles"] == 1
    assert notes["skipped"] == [room.guids["Sketch"]] and notes["degenerate_facets_dropped"] == 0
    assert notes["units"] == "m" and notes["ifc_file_unit_m"] == pytest.approx(0.001)  # the file is in mm


def test_classes_and_exclude_select_products(room) -> None:
    from stages.io.ifc import IfcParams, read_ifc

    def read(**params):
        return read_ifc(ReadRequest(room.path, "bim", "as-designed", None, "", params=IfcParams(**params)))

    assert [ds.meta["name"] for ds in read(classes=["IfcSlab"])] == [FLOOR]
    assert FLOOR not in [ds.meta["name"] for ds in read(exclude=["IfcSlab"])]
    merged = read(merge=True)
    assert merged.n_elements == 5 * 12 and merged.meta["products"] == "5"
    with pytest.raises(InputError, match="'IfcWal' is not an entity of the schema IFC4"):
        read(classes=["IfcWal"])


def test_without_ifcopenshell_the_error_says_what_to_install(room, monkeypatch) -> None:
    from stages.io.ifc import open_ifc

    monkeypatch.setitem(sys.modules, "ifcopenshell", None)  # import ifcopenshell now raises ImportError
    with pytest.raises(InputError, match=re.escape("pip install 'gdt-pipeline[bim]'")):
        open_ifc(room.path)


def test_a_truncated_file_and_a_text_file_are_input_errors_naming_the_file(registry, room, tmp_path) -> None:
    data = room.path.read_bytes()
    cut = tmp_path / "cut.ifc"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut\.ifc: truncated IFC file"):
        read_datasets(cut, registry, name="bim")
    text = tmp_path / "notes.ifc"
    text.write_text("wall schedule: A, B, C, D\n")
    with pytest.raises(InputError, match=r"notes\.ifc: not an IFC file"):
        read_datasets(text, registry, name="bim")


def _scan(registry, room: Room, path: Path, seed: int = 3, sigma: float = 0.002) -> None:
    """A terrestrial scan from the room's centre of the room without ``GONE`` (rays on a Fibonacci sphere, Gaussian
    noise): through the gap the scanner sees a neighbour's facade 1.5 m beyond, as a real one would."""
    import open3d as o3d
    import trimesh

    kept = [ds for ds in read_datasets(room.path, registry, name="bim") if ds.meta["name"] != GONE]
    facade = trimesh.creation.box(extents=(14.0, 0.3, 9.0))
    facade.apply_translation((2.0, 4.65, 1.0))
    scene = o3d.t.geometry.RaycastingScene()
    for v, f in [(ds.points, ds.faces) for ds in kept] + [(facade.vertices, facade.faces)]:
        scene.add_triangles(o3d.core.Tensor(np.asarray(v, np.float32)), o3d.core.Tensor(np.asarray(f, np.uint32)))
    n = 60_000
    k = np.arange(n) + 0.5
    z, phi = 1 - 2 * k / n, np.pi * (1 + 5**0.5) * k
    dirs = np.column_stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z])
    rays = np.hstack([np.broadcast_to(EYE, dirs.shape), dirs]).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    hit = np.isfinite(t)  # rays into the open sky (no ceiling) return nothing
    pts = np.asarray(EYE) + dirs[hit] * t[hit, None]
    write_points_ply(path, pts + np.random.default_rng(seed).normal(0, sigma, pts.shape))


WORKFLOW = """\
name: ifc-room
twin: twin
seed: 5
units: m  # the IFC reader returns metres whatever the file's length unit
epochs:
  - id: E1
    role: as-designed
    inputs: [{path: room.ifc, name: bim}]
  - id: E2
    role: as-is
    inputs: [{path: scan.ply, name: scan, viewpoints: [[2.0, 1.5, 1.5]]}]
stages:
  - uses: constant
    role: as-designed
    with: {model: isotropic, sigma: 0.001}
  - uses: identity
    role: as-is
  - uses: constant
    role: as-is
    with: {model: isotropic, sigma: 0.002}
  - uses: manual_box
    role: as-is
    with: {lower: [-0.5, -0.5, -0.5], upper: [4.5, 3.5, 3.0]}
  - uses: nearest
    role: as-is
  - uses: bhattacharyya
    role: as-is
  - uses: fixed
    role: as-is
    with: {tau: 10.0}
  - uses: keep_unchanged
"""


def test_a_wall_missing_from_the_scan_is_logged_removed_by_its_global_id(registry, room, tmp_path) -> None:
    (tmp_path / "room.ifc").write_bytes(room.path.read_bytes())
    _scan(registry, room, tmp_path / "scan.ply")
    workflow = tmp_path / "workflow.yaml"
    workflow.write_text(textwrap.dedent(WORKFLOW))
    result = run_workflow(workflow, registry=registry)
    store = TwinStore.open(result.twin)
    identities = store.identities("E1")
    assert {ident["global_id"] for ident in identities.values()} == {room.guids[n] for n in [*WALLS, FLOOR]}
    gone_key = f"E1_bim_IfcWall_{GONE.replace(' ', '_')}"
    assert identities[gone_key] == {"name": GONE, "global_id": room.guids[GONE], "ifc_class": "IfcWall",
                                    "ifc_file_schema": "IFC4"}

    log = run_gdt("log", str(result.twin))
    assert log.returncode == 0, log.stderr
    removal_lines = [line for line in log.stdout.splitlines() if ": removed: " in line or ": changed: " in line]
    assert removal_lines == [f"E2: removed: IfcWall 'Wall C' GlobalId {room.guids[GONE]} ({gone_key}: 12 of its 12 "
                             "facets)"], log.stdout
    assert all(room.guids[n] not in log.stdout for n in [*WALLS, FLOOR] if n != GONE)

    as_json = run_gdt("log", "--json", str(result.twin))
    assert as_json.returncode == 0, as_json.stderr
    epochs = {e["epoch"]: e for e in json.loads(as_json.stdout)}
    assert epochs["E1"]["identified_removals"] == []
    (found,) = epochs["E2"]["identified_removals"]
    assert found["identity"]["global_id"] == room.guids[GONE] and found["kind"] == "mesh"
    assert found["removed"] / found["of"] > 0.5
    audit = audit_twin(result.twin, registry=registry)  # the IFC read again as recorded gives the same twin
    assert audit.ok and [e.verdict for e in audit.epochs] == ["match", "match"]
