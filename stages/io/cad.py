"""STEP and IGES (B-rep CAD) through cascadio, a packaged OpenCASCADE that tessellates the model to a GLB in memory:
one triangle-mesh dataset per top-level part (an instance of a component of the file's top assembly), named by its
product name, with the instance's placement baked into the vertices.

Units: OpenCASCADE converts the file's length unit (inch, millimetre, ...) to millimetres; cascadio then writes a
STEP model in metres (glTF's unit) but an IGES model still in millimetres (cascadio 0.1.1), which this reader
scales. The data come back in metres, whatever the file's unit, and the reader says so (``units`` note), so the
engine does not scale them by the workflow's ``units:``. The file's own unit is kept as ``cad_file_units``.

Tessellation: ``tolerance`` is the largest distance between a facet and the B-rep surface, in metres whatever the
file's unit (cascadio's ``tol_linear`` is in OpenCASCADE's millimetres: the reader converts), and
``angular_tolerance_deg`` the largest angle between the normals of neighbouring facets. The file is checked before
OpenCASCADE parses it (OpenCASCADE prints its complaints on the console and cascadio returns nothing), and every
part's triangles after: indices in range, finite, degenerate facets dropped and counted.
"""

from __future__ import annotations

import json
import logging
import math
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gdt_pipeline import Dataset, InputError, ReaderSpec, ReadRequest

from .mesh import check_triangles, drop_degenerate, merged_mesh
from .step_file import check_spf

log = logging.getLogger(__name__)

CAD_VERSION = "1.0.0"
STEP_SUFFIXES, IGES_SUFFIXES = (".step", ".stp"), (".igs", ".iges")
MM_PER_M = 1000.0
# part names listed in the provenance; past this only their count (an assembly may hold thousands of screws)
MAX_LISTED = 20
_SI_PREFIX = {"$": "m", ".MILLI.": "mm", ".CENTI.": "cm", ".DECI.": "dm", ".MICRO.": "um", ".KILO.": "km"}
_NAMED_UNIT = {"INCH": "in", "FOOT": "ft", "MILLIMETRE": "mm", "MILLIMETER": "mm", "METRE": "m", "METER": "m"}
# IGES global parameter 14 (units flag); 3 means "the name in parameter 15"
_IGES_UNIT = {1: "in", 2: "mm", 4: "ft", 5: "mi", 6: "m", 7: "km", 8: "mil", 9: "um", 10: "cm", 11: "uin"}
_LENGTH_UNIT = re.compile(rb"#(\d+)\s*=\s*\(([^;]*\bLENGTH_UNIT\b[^;]*)\)\s*;")
_UNIT_CONTEXT = re.compile(rb"GLOBAL_UNIT_ASSIGNED_CONTEXT\s*\(\s*\(([^)]*)\)")
_HOLLERITH = re.compile(r"\s*(\d+)H")


class CadParams(BaseModel):
    """Parameters of the cascadio STEP/IGES reader."""

    model_config = ConfigDict(extra="forbid")
    tolerance: float = Field(1e-4, gt=0, description="Largest distance between a facet and the B-rep surface, in "
                                                     "metres whatever the file's unit (linear deflection; 0.1 mm).")
    angular_tolerance_deg: float = Field(5.0, gt=0, le=90, description="Largest angle between the normals of "
                                                                       "neighbouring facets (angular deflection).")
    merge_parts: bool = Field(False, description="One dataset for the whole file instead of one per top-level part "
                                                 "(the parts' names are lost).")


@dataclass(frozen=True)
class CadPart:
    """One top-level part as tessellated: product and instance names, vertices (metres) and facets."""

    name: str
    instance: str
    vertices: np.ndarray
    faces: np.ndarray


def accepts_cad(path: Path, kind: str | None) -> bool:
    """A CAD model tessellates to a mesh: refused only when the input asks for points."""
    return kind != "points"


def check_iges(path: Path, data: bytes) -> None:
    """A fixed-form IGES file ends with its terminate record, which counts the lines of every section."""
    lines = [line for line in data.decode("latin-1").splitlines() if line.strip()]
    if not lines or len(lines[0]) < 73 or lines[0][72] != "S":
        raise InputError(f"{path}: not an IGES file in the ASCII fixed form (line 1, column 73: no 'S' section)")
    last = lines[-1]
    declared = re.findall(r"([SGDP])\s*(\d+)", last[:32]) if len(last) >= 73 and last[72] == "T" else []
    if len(declared) != 4:
        raise InputError(f"{path}: truncated IGES file: the last line is not a terminate ('T') record "
                         f"({len(lines)} lines)")
    found = {s: sum(1 for line in lines if len(line) >= 73 and line[72] == s) for s in "SGDP"}
    for section, count in declared:
        if found[section] != int(count):
            raise InputError(f"{path}: the IGES terminate record declares {count} '{section}' lines, the file "
                             f"holds {found[section]}: truncated or edited")


def step_length_units(data: bytes) -> str:
    """The length unit(s) the STEP file's representation contexts declare ("in", "mm", "m", ...; "in,mm" when its
    parts differ), or "unknown"."""
    units = {m.group(1): _unit_name(m.group(2).decode("latin-1")) for m in _LENGTH_UNIT.finditer(data)}
    used = {units[ref] for m in _UNIT_CONTEXT.finditer(data) for ref in re.findall(rb"#(\d+)", m.group(1))
            if ref in units}
    return ",".join(sorted(used)) or "unknown"


def _unit_name(entity: str) -> str:
    named = re.search(r"CONVERSION_BASED_UNIT\s*\(\s*'([^']*)'", entity)
    if named:
        return _NAMED_UNIT.get(named.group(1).upper(), named.group(1).lower())
    si = re.search(r"SI_UNIT\s*\(\s*(\$|\.\w+\.)\s*,\s*\.METRE\.", entity)
    return _SI_PREFIX.get(si.group(1), si.group(1)) if si else "unknown"


def iges_length_units(data: bytes) -> str:
    """The model unit an IGES file's global section names (parameter 14, or 15 for flag 3), or "unknown"."""
    text = "".join(line[:72] for line in data.decode("latin-1").splitlines() if len(line) >= 73 and line[72] == "G")
    fields, i = [], 0
    while i < len(text) and len(fields) < 15:
        hollerith = _HOLLERITH.match(text, i)
        if hollerith:
            n = int(hollerith.group(1))
            value, i = text[hollerith.end():hollerith.end() + n], hollerith.end() + n
        else:
            ends = [k for k in (text.find(",", i), text.find(";", i)) if k >= 0]
            value, i = text[i:min(ends, default=len(text))].strip(), min(ends, default=len(text))
        fields.append(value)
        while i < len(text) and text[i] not in ",;":
            i += 1
        i += 1  # past the delimiter
    # other delimiters than the defaults (parameters 1 and 2) are legal but rare: the unit then stays unknown
    if len(fields) < 15 or fields[0] not in ("", ",") or not fields[13].strip().isdigit():
        return "unknown"
    flag = int(fields[13])
    if flag == 3:
        return fields[14].strip().lower() or "unknown"
    return _IGES_UNIT.get(flag, "unknown")


def tessellate(path: Path, data: bytes, fmt: str, params: CadParams) -> bytes:
    """The model tessellated by OpenCASCADE (through cascadio) to the params' tolerances, as GLB bytes."""
    try:
        import cascadio
    except ImportError:
        raise InputError(f"reading {fmt} needs cascadio: pip install 'gdt-pipeline[cad]'") from None
    # use_parallel off: the facets come out in the same order on every run (provenance, audits)
    glb = cascadio.load(data, file_type=fmt.lower(), tol_linear=params.tolerance * MM_PER_M,
                        tol_angular=math.radians(params.angular_tolerance_deg), tol_relative=False,
                        merge_primitives=True, use_parallel=False)
    if not glb:
        raise InputError(f"{path}: OpenCASCADE could not read or transfer the {fmt} model (cascadio returned "
                         f"nothing; OpenCASCADE's own message is printed on the console)")
    return glb


def glb_document(glb: bytes) -> tuple[dict[str, Any], bytes]:
    """The JSON document and binary chunk of a GLB."""
    # Decoded here rather than by trimesh's GLB loader: trimesh renames a mesh placed several times (gusset_1,
    # gusset_2, ...) and keeps node names instead of the product names the parts are known by, and it labels an
    # IGES model metres when cascadio wrote millimetres; the few glTF features cascadio writes are all read here.
    magic, _, length = struct.unpack_from("<4sII", glb, 0)
    json_length, json_type = struct.unpack_from("<I4s", glb, 12)
    if magic != b"glTF" or length != len(glb) or json_type != b"JSON":
        raise ValueError(f"not a whole GLB ({len(glb)} bytes, header says {length})")
    doc = json.loads(glb[20:20 + json_length])
    rest = 20 + json_length
    binary = b""
    if rest + 8 <= len(glb):
        bin_length, bin_type = struct.unpack_from("<I4s", glb, rest)
        binary = glb[rest + 8:rest + 8 + bin_length] if bin_type == b"BIN\x00" else b""
    return doc, binary


_COMPONENT = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}
_WIDTH = {"SCALAR": 1, "VEC3": 3}


def _accessor(doc: dict[str, Any], binary: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype, width = np.dtype(_COMPONENT[acc["componentType"]]), _WIDTH[acc["type"]]
    if view.get("byteStride", dtype.itemsize * width) != dtype.itemsize * width:
        raise ValueError("interleaved buffer view")
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    if start + acc["count"] * width * dtype.itemsize > min(len(binary), view.get("byteOffset", 0) + view["byteLength"]):
        raise ValueError(f"accessor {index} reaches past its buffer")
    return np.frombuffer(binary, dtype, acc["count"] * width, start).reshape(-1, width)


def _local(node: dict[str, Any]) -> np.ndarray:
    """A node's placement in its parent: a column-major matrix, or translation, rotation (x, y, z, w) and scale."""
    if "matrix" in node:
        return np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T
    x, y, z, w = node.get("rotation", (0.0, 0.0, 0.0, 1.0))
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    out = np.eye(4)
    out[:3, :3] = rot * np.asarray(node.get("scale", (1.0, 1.0, 1.0)), dtype=np.float64)
    out[:3, 3] = node.get("translation", (0.0, 0.0, 0.0))
    return out


def weld(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices at exactly the same place made one, in first-occurrence order: OpenCASCADE meshes each B-rep face
    on its own, so the faces of a solid share edge points but not vertices, and the mesh would not be closed."""
    _, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return vertices[first[order]], rank[inverse.reshape(-1)][faces]


def _primitive(path: Path, doc: dict[str, Any], binary: bytes, prim: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """One triangle primitive's welded vertices (float32, as written) and facets."""
    vertices = _accessor(doc, binary, prim["attributes"]["POSITION"])
    if "indices" in prim:
        faces = _accessor(doc, binary, prim["indices"]).astype(np.int64).reshape(-1, 3)
    else:
        faces = np.arange(len(vertices) // 3 * 3, dtype=np.int64).reshape(-1, 3)
    check_triangles(path, vertices.astype(np.float64), faces)
    # welded before the placement is applied: equal float32 inputs stay exactly equal whatever the arithmetic
    return weld(vertices, faces)


def _part_roots(doc: dict[str, Any]) -> list[tuple[int, np.ndarray]]:
    """The top-level parts' nodes with their parents' placement: an assembly is one node holding its components,
    so single nodes without a mesh are stepped through until the parts show."""
    nodes = doc.get("nodes", [])
    roots = [(i, np.eye(4)) for i in doc.get("scenes", [{}])[doc.get("scene", 0)].get("nodes", [])]
    for _ in range(len(nodes)):
        if len(roots) != 1 or "mesh" in nodes[roots[0][0]] or not nodes[roots[0][0]].get("children"):
            break
        index, placement = roots[0]
        roots = [(child, placement @ _local(nodes[index])) for child in nodes[index]["children"]]
    return roots


def _subtree_mesh(path: Path, doc: dict[str, Any], binary: bytes, root: int, placement: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, int]:
    """Every triangle under a part's node, placed in the file's frame: vertices, facets, non-triangle primitives."""
    nodes, meshes = doc["nodes"], doc.get("meshes", [])
    verts, faces, skipped, n = [], [], 0, 0
    stack, seen = [(root, placement)], set()
    while stack:
        index, parent = stack.pop()
        if index in seen:  # glTF forbids a node under two parents; a cycle must not loop forever
            raise ValueError(f"node {index} reached twice")
        seen.add(index)
        node = nodes[index]
        here = parent @ _local(node)
        for prim in meshes[node["mesh"]]["primitives"] if "mesh" in node else []:
            if prim.get("mode", 4) != 4:
                skipped += 1  # lines or points (free edges, vertices): no surface to scan
                continue
            v, f = _primitive(path, doc, binary, prim)
            verts.append(v.astype(np.float64) @ here[:3, :3].T + here[:3, 3])
            faces.append(f + n)
            n += len(v)
        stack += [(child, here) for child in reversed(node.get("children", []))]
    if not faces:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), skipped
    return np.vstack(verts), np.vstack(faces), skipped


def glb_parts(path: Path, glb: bytes, scale: float = 1.0) -> tuple[list[CadPart], int]:
    """The top-level parts of cascadio's GLB (coordinates times ``scale``), and the non-triangle primitives
    skipped; a GLB not shaped as cascadio writes it is an InputError."""
    try:
        doc, binary = glb_document(glb)
        parts, skipped = [], 0
        for k, (index, placement) in enumerate(_part_roots(doc)):
            node = doc["nodes"][index]
            mesh_name = doc["meshes"][node["mesh"]].get("name") if "mesh" in node else None
            # a leaf's node is the instance (STEP's NAUO), its mesh the product; an assembly node has only its name
            name = mesh_name or node.get("name") or f"part_{k}"
            verts, faces, n = _subtree_mesh(path, doc, binary, index, placement)
            skipped += n
            parts.append(CadPart(name=name, instance=node.get("name", ""), vertices=verts * scale, faces=faces))
    except (KeyError, IndexError, TypeError, ValueError, struct.error) as exc:
        raise InputError(f"{path}: cascadio's GLB is not as expected ({type(exc).__name__}: {exc})") from exc
    return parts, skipped


def _checked(path: Path, parts: list[CadPart]) -> tuple[list[CadPart], int]:
    """The parts with triangles, degenerate facets dropped; the count dropped."""
    out, dropped = [], 0
    for part in parts:
        if not len(part.faces):
            log.warning("%s: part %r has no triangles (no B-rep faces): skipped", path, part.name)
            continue
        try:
            faces, n = drop_degenerate(path, part.vertices, part.faces)
        except InputError as exc:
            raise InputError(f"part {part.name!r}: {exc}") from exc
        dropped += n
        out.append(CadPart(part.name, part.instance, part.vertices, faces))
    if not out:
        raise InputError(f"{path}: no triangles: the model holds no B-rep faces (empty, or only curves and points)")
    return out, dropped


def _listed(names: list[str]) -> list[str]:
    return names[:MAX_LISTED] + ([f"... {len(names) - MAX_LISTED} more"] if len(names) > MAX_LISTED else [])


def read_cad(req: ReadRequest) -> list[Dataset] | Dataset:
    """One mesh dataset per top-level part of a STEP file (its product name in ``meta``), in metres; one dataset for
    the whole model with ``merge_parts`` or for an IGES file (which reaches cascadio's GLB without part names)."""
    path, params = req.path, req.params
    data = path.read_bytes()
    iges = path.suffix.lower() in IGES_SUFFIXES
    fmt = "IGES" if iges else "STEP"
    check_iges(path, data) if iges else check_spf(path, "STEP")
    file_units = iges_length_units(data) if iges else step_length_units(data)
    glb = tessellate(path, data, fmt, params)
    # cascadio 0.1.1 writes IGES in OpenCASCADE's millimetres but STEP in metres (tests/test_read_cad.py checks both)
    parts, skipped = glb_parts(path, glb, scale=1 / MM_PER_M if iges else 1.0)
    parts, dropped = _checked(path, parts)
    names = [p.name for p in parts]
    req.report(units="m", cad_format=fmt, cad_file_units=file_units, tolerance_m=params.tolerance,
               angular_tolerance_deg=params.angular_tolerance_deg, parts=len(parts), part_names=_listed(names),
               facets=int(sum(len(p.faces) for p in parts)), degenerate_facets_dropped=dropped,
               **({"non_triangle_primitives_skipped": skipped} if skipped else {}))
    meta = {"cad_format": fmt, "cad_file_units": file_units}
    if params.merge_parts or iges:
        return merged_mesh(req, [(p.vertices, p.faces) for p in parts], {**meta, "parts": str(len(parts))})
    return [Dataset(name=p.name, role=req.role, points=p.vertices, faces=p.faces,
                    meta={"name": p.name, "instance": p.instance, **meta}) for p in parts]





READER = ReaderSpec(name="cascadio_cad", version=CAD_VERSION, params=CadParams, read=read_cad, accepts=accepts_cad,
                    extensions=(".step", ".stp", ".igs", ".iges"),
                    description="STEP/IGES B-rep CAD through cascadio (OpenCASCADE), tessellated to `tolerance` "
                                "metres: one mesh per top-level part named by its product (IGES: one mesh), in "
                                "metres whatever the file's unit.")
