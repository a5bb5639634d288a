"""The STEP/IGES reader (cascadio): a STEP part against the STL of the same part, an assembly against its own product
structure, the tolerance in metres whatever the file's unit, IGES in metres too, bad files refused, and the units
the reader states honoured by the engine."""

from __future__ import annotations

import re
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import trimesh

from gdt_pipeline import InputError, ReadRequest
from gdt_pipeline.plugins import load_registry
from gdt_pipeline.runner import read_datasets
from gdt_pipeline.runner.inputs import read_input
from gdt_pipeline.runner.plan import EpochPlan, InputPlan, RunPlan
from stages.io.cad import CadParams, read_cad

from .conftest import SHARED_DATA

pytest.importorskip("cascadio")
CAD = SHARED_DATA / "cad_meshes"
needs_cad_data = pytest.mark.skipif(not CAD.is_dir(), reason="../shared/data/cad_meshes absent")
INCH = 0.0254  # both STEP files declare CONVERSION_BASED_UNIT('INCH'); featuretype.STL is in inches too


def _read(path: Path, **params: object) -> tuple[list, dict]:
    req = ReadRequest(path, "cad", "as-designed", None, "", params=CadParams(**params))
    out = read_cad(req)
    return (out if isinstance(out, list) else [out]), req.notes


def _mesh(ds) -> trimesh.Trimesh:
    return trimesh.Trimesh(ds.points, ds.faces, process=False)


def _entities(text: str) -> dict[int, tuple[str, str]]:
    """Simple (not complex) STEP entities: id -> (type, parameters)."""
    return {int(m.group(1)): (m.group(2), m.group(3))
            for m in re.finditer(r"#(\d+)\s*=\s*(\w+)\s*\(([^;]*)\)\s*;", text)}


def _refs(body: str) -> list[int]:
    return [int(r) for r in re.findall(r"#(\d+)", body)]


def _product_instances(ent: dict[int, tuple[str, str]]) -> Counter:
    """Product name of every NEXT_ASSEMBLY_USAGE_OCCURRENCE's child: NAUO -> PRODUCT_DEFINITION -> formation ->
    PRODUCT."""
    out: Counter = Counter()
    for kind, body in ent.values():
        if kind == "NEXT_ASSEMBLY_USAGE_OCCURRENCE":
            formation = _refs(ent[_refs(body)[1]][1])[0]
            product = _refs(ent[formation][1])[0]
            out[re.match(r"\s*'([^']*)'", ent[product][1]).group(1)] += 1
    return out


def _solid_extents(ent: dict[int, tuple[str, str]]) -> list[tuple[float, ...]]:
    """Sorted extents (file units) of the B-rep vertices each MANIFOLD_SOLID_BREP reaches."""
    out = []
    for root, (kind, _) in ent.items():
        if kind != "MANIFOLD_SOLID_BREP":
            continue
        seen, stack = set(), [root]
        while stack:
            k = stack.pop()
            if k not in seen and k in ent:
                seen.add(k)
                stack += _refs(ent[k][1])
        pts = np.array([[float(x) for x in re.search(r"\(([^()]*)\)\s*$", ent[_refs(ent[k][1])[0]][1]).group(1)
                         .split(",")] for k in seen if ent[k][0] == "VERTEX_POINT"])
        out.append(tuple(np.sort(pts.max(0) - pts.min(0))))
    return sorted(out)


def _iges(size: float, unit_flag: int, unit_name: str, drop_last: bool = False) -> str:
    """A fixed-form IGES file of one flat bilinear B-spline patch (entity 128) of ``size`` file units square."""
    def line(text: str, section: str, n: int) -> str:
        return f"{text:<72}{section}{n:7d}"
    g = (f"1H,,1H;,4Htest,8Htest.igs,4Htest,3H1.0,32,38,6,308,15,4Htest,1.0,{unit_flag},{len(unit_name)}H"
         f"{unit_name},1,0.1,15H20240101.120000,1.0E-6,{size},2Hme,2Hme,11,0,15H20240101.120000;")
    gl = [line(g[i:i + 72], "G", k + 1) for k, i in enumerate(range(0, len(g), 72))]
    s = float(size)
    p = ["128,1,1,1,1,0,0,1,0,0,0.,0.,1.,1.,0.,0.,1.,1.,1.,1.,1.,1.,",
         f"0.,0.,0.,{s},0.,0.,0.,{s},0.,{s},{s},0.,0.,1.,0.,1.;"]
    pl = [f"{t:<64} {1:>7}P{k + 1:7d}" for k, t in enumerate(p)]
    d = [line("".join(f"{v:>8}" for v in (128, 1, 0, 0, 0, 0, 0, 0, "00000000")), "D", 1),
         line("".join(f"{v:>8}" for v in (128, 0, 0, len(pl), 0, "", "", "", 0)), "D", 2)]
    t = [line(f"S{1:7d}G{len(gl):7d}D{len(d):7d}P{len(pl):7d}", "T", 1)]
    lines = [line("one flat patch", "S", 1)] + gl + d + pl + ([] if drop_last else t)
    return "\n".join(lines) + "\n"


@pytest.mark.shared_data
@needs_cad_data
def test_featuretype_step_matches_its_stl_in_metres() -> None:
    parts, notes = _read(CAD / "featuretype.STEP", tolerance=1e-4, angular_tolerance_deg=5.0)
    stl = trimesh.load(CAD / "featuretype.STL", process=False)
    assert [p.meta["name"] for p in parts] == ["featuretype"] and notes["cad_file_units"] == "in"
    assert notes["units"] == "m" and notes["tolerance_m"] == 1e-4 and notes["parts"] == 1
    mesh = _mesh(parts[0])
    assert mesh.is_watertight
    # like with like: the STL's square inches in square metres (53.8274 in^2 = 0.0347273 m^2; STEP 0.0347331 m^2)
    assert mesh.area == pytest.approx(stl.area * INCH**2, rel=0.005)
    # 5 x 2.5 x 1.375 in = 0.127 x 0.0635 x 0.034925 m, within float32 in metres
    np.testing.assert_allclose(mesh.bounds, stl.bounds * INCH, atol=1e-6)


@pytest.mark.shared_data
@needs_cad_data
def test_box_sides_parts_are_the_files_product_structure() -> None:
    path = CAD / "box_sides.STEP"
    ent = _entities(path.read_text(encoding="latin-1"))
    parts, notes = _read(path, tolerance=1e-4)
    # 6 products placed 10 times: gusset x4, side_long x2, box_base, side_short, side_short_B, box_top
    assert Counter(p.meta["name"] for p in parts) == _product_instances(ent)
    assert notes["parts"] == 10 and [p.meta["instance"] for p in parts] == [f"NAUO{k}" for k in range(1, 11)]
    for p in parts:
        assert np.isfinite(p.points).all() and _mesh(p).is_watertight, p.meta
    # each product's extents (its placements only turn it by right angles) are those of its solid's B-rep vertices
    by_product = {p.meta["name"]: tuple(np.sort(np.ptp(p.points, axis=0))) for p in parts}
    solids = [tuple(np.array(e) * INCH) for e in _solid_extents(ent)]

    def order(extents: list) -> list:  # sorted on values rounded to 10 um: float32 noise must not reorder them
        return sorted(extents, key=lambda e: tuple(np.round(e, 5)))
    np.testing.assert_allclose(order(list(by_product.values())), order(solids), atol=1e-6)
    # placed: the box is as long and wide as its base and as tall as its sides (7.25 x 4.5 x 3.75 in)
    every = np.vstack([p.points for p in parts])
    base, side = sorted(by_product["box_base"]), sorted(by_product["side_long"])
    np.testing.assert_allclose(np.ptp(every, axis=0), [base[2], base[1], side[1]], atol=1e-6)
    coarse, _ = _read(path, tolerance=1e-3, angular_tolerance_deg=15.0)
    fine, _ = _read(path, tolerance=1e-5, angular_tolerance_deg=2.0)
    area = [sum(_mesh(p).area for p in run) for run in (coarse, fine)]
    assert sum(len(p.faces) for p in fine) > 2 * sum(len(p.faces) for p in coarse)
    assert area[0] == pytest.approx(area[1], rel=0.005)  # 0.189532 and 0.189529 m^2


@pytest.mark.shared_data
@needs_cad_data
def test_the_engine_names_the_parts_and_the_tolerance_sets_the_facets() -> None:
    registry = load_registry()
    assert registry.reader("cascadio_cad") in registry.readers_for(CAD / "box_sides.STEP", None)
    parts = read_datasets(CAD / "box_sides.STEP", registry, name="cad", role="as-designed")
    assert [p.name for p in parts][:4] == ["cad_box_base", "cad_side_long", "cad_side_long_2", "cad_side_short"]
    assert parts[1].meta["name"] == parts[2].meta["name"] == "side_long" and parts[0].meta["cad_file_units"] == "in"
    assert parts[0].source.reader == "cascadio_cad" and parts[0].source.notes["units"] == "m"
    # the input's `with:` reaches the reader. The angle is opened up so that the distance alone sets the facets:
    # at 5 degrees OpenCASCADE gives 13488, 12816, 18214 facets for 1, 0.1, 0.01 mm (not monotonic)
    facets = [len(read_datasets(CAD / "featuretype.STEP", registry, name="cad", role="as-designed",
                                params={"tolerance": t, "angular_tolerance_deg": 90})[0].faces)
              for t in (1e-3, 1e-4, 1e-5)]
    assert facets[0] < facets[1] < facets[2]  # 932 < 2100 < 8158
    with pytest.raises(InputError, match=r"with\.tolerance"):
        read_datasets(CAD / "featuretype.STEP", registry, name="cad", role="as-designed", params={"tolerance": -1})
    merged, notes = _read(CAD / "box_sides.STEP", merge_parts=True)
    assert len(merged) == 1 and merged[0].name == "cad" and len(merged[0].faces) == notes["facets"]


@pytest.mark.shared_data
@needs_cad_data
def test_the_tolerance_is_in_metres_whatever_the_files_unit(tmp_path: Path) -> None:
    text = (CAD / "featuretype.STEP").read_text(encoding="latin-1")
    # the same numbers read as metres: a part 1 / 0.0254 times larger, to be meshed 1 / 0.0254 times coarser
    metres = re.sub(r"\(\s*CONVERSION_BASED_UNIT \( 'INCH', #\d+ \) LENGTH_UNIT \( \) NAMED_UNIT \( #\d+ \) \)",
                    "( LENGTH_UNIT ( ) NAMED_UNIT ( * ) SI_UNIT ( $, .METRE. ) )", text)
    (tmp_path / "big.step").write_text(metres, encoding="latin-1")
    small, small_notes = _read(CAD / "featuretype.STEP", tolerance=1e-4)
    big, big_notes = _read(tmp_path / "big.step", tolerance=1e-4 / INCH)
    assert big_notes["cad_file_units"] == "m" and big_notes["facets"] == small_notes["facets"]
    np.testing.assert_allclose(_mesh(big[0]).bounds * INCH, _mesh(small[0]).bounds, atol=1e-6)
    assert _mesh(big[0]).area * INCH**2 == pytest.approx(_mesh(small[0]).area, rel=1e-5)


def test_iges_is_read_in_metres(tmp_path: Path) -> None:
    # cascadio 0.1.1 writes IGES in millimetres (STEP in metres): the reader scales, this pins it
    for size, flag, name, side in ((10.0, 2, "MM", 0.010), (10.0, 1, "IN", 10 * INCH), (2.0, 6, "M", 2.0)):
        path = tmp_path / f"patch_{name}.igs"
        path.write_text(_iges(size, flag, name))
        parts, notes = _read(path)
        assert notes["cad_format"] == "IGES" and notes["cad_file_units"] == name.lower() and len(parts) == 1
        assert _mesh(parts[0]).area == pytest.approx(side**2, rel=1e-9)
        np.testing.assert_allclose(np.ptp(parts[0].points, axis=0), [side, side, 0.0], atol=1e-9 * side)
    cut = tmp_path / "cut.igs"
    cut.write_text(_iges(10.0, 2, "MM", drop_last=True))
    with pytest.raises(InputError, match="truncated IGES"):
        _read(cut)


@pytest.mark.shared_data
@needs_cad_data
def test_a_bad_step_is_an_input_error_never_data(tmp_path: Path) -> None:
    data = (CAD / "box_sides.STEP").read_bytes()
    registry = load_registry()
    half = tmp_path / "half.step"
    half.write_bytes(data[:len(data) // 2])
    with pytest.raises(InputError, match="truncated STEP file: it does not end with 'END-ISO-10303-21;'"):
        read_datasets(half, registry, name="cad", role="as-designed")
    # cut in the middle yet closed: the check passes, OpenCASCADE cannot parse it, and nothing comes back
    closed = tmp_path / "closed.step"
    closed.write_bytes(data[:len(data) // 2] + b"\nENDSEC;\nEND-ISO-10303-21;\n")
    with pytest.raises(InputError, match="OpenCASCADE could not read or transfer the STEP model"):
        read_datasets(closed, registry, name="cad", role="as-designed")
    empty = tmp_path / "empty.step"
    empty.write_bytes(data[:data.index(b"DATA;") + 5] + b"\nENDSEC;\nEND-ISO-10303-21;\n")
    with pytest.raises(InputError, match="could not read or transfer"):
        read_datasets(empty, registry, name="cad", role="as-designed")


def test_missing_cascadio_names_the_extra(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "patch.igs"
    path.write_text(_iges(10.0, 2, "MM"))
    monkeypatch.setitem(sys.modules, "cascadio", None)
    with pytest.raises(InputError, match=r"reading IGES needs cascadio: pip install 'gdt-pipeline\[cad\]'"):
        _read(path)


@pytest.mark.shared_data
@needs_cad_data
def test_the_engine_keeps_the_units_the_reader_states(tmp_path: Path) -> None:
    registry = load_registry()

    def plan(input_units: str, given: bool = False) -> RunPlan:
        inp = InputPlan(path=CAD / "featuretype.STEP", name="cad", units=input_units, units_given=given)
        epoch = EpochPlan(id="E0", index=0, role="as-designed", inputs=[inp], stages=[])
        return RunPlan(name="t", workflow_path=tmp_path / "w.yaml", workflow_sha256="", base_dir=tmp_path, seed=0,
                       units="mm", up_axis="z", epochs=[epoch])

    # a twin in millimetres, the input's units: left to the workflow's: the metres the reader states are scaled
    run = plan("mm")
    (ds,), _ = read_input(run, registry, run.epochs[0], 0, "")
    assert ds.source.units == "m" and ds.source.scale == 1000.0
    np.testing.assert_allclose(np.ptp(ds.points, axis=0), [127.0, 63.5, 34.925], atol=1e-3)
    for written in ("in", "mm"):  # written on the input, even the twin's own units contradict the file
        run = plan(written, given=True)
        with pytest.raises(InputError, match=rf"units: {written}.*'m'"):
            read_input(run, registry, run.epochs[0], 0, "")
    run = plan("m", given=True)
    assert read_input(run, registry, run.epochs[0], 0, "")[0][0].source.scale == 1000.0
