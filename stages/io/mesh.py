"""Triangle meshes through trimesh, checked before and after: trimesh trusts a header's counts and returns whatever
it could parse, so each format's declared sizes are checked against the file first and trimesh's result against
the file's own counts after. Degenerate facets (repeated vertices, zero area) are dropped and counted: a facet
without a normal cannot be scored.
"""

from __future__ import annotations

import logging
import re
import struct
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gdt_pipeline import Dataset, InputError, ReaderSpec, ReadRequest
from gdt_pipeline.geometry import triangle_normals

from .ply import read_ply
from .ply_header import face_count
from .text import nonfinite
from .version import VERSION

log = logging.getLogger(__name__)
# Relative to its longest edge squared, a facet's doubled area below this is zero in float64 arithmetic.
DEGENERATE_AREA = 1e-12
_OBJ_FACE = re.compile(rb"^[ \t]*f[ \t]", re.MULTILINE)
_OFF_TOKEN = re.compile(rb"[^\s#][^\s]*|#[^\n]*")


def check_stl(path: Path) -> None:
    """A binary STL holds exactly 84 + 50 × its declared triangle count bytes; an ASCII STL must be text."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(1024)
    n = struct.unpack_from("<I", head, 80)[0] if size >= 84 else None
    if n is not None and 84 + 50 * n == size:
        return
    if head.lstrip().lower().startswith(b"solid") and b"\x00" not in head:
        return  # ASCII: trimesh parses it; the facet count is checked on what it returns
    if n is None:
        raise InputError(f"{path}: {size} bytes: shorter than a binary STL's 84-byte header and not ASCII STL")
    raise InputError(f"{path}: binary STL header (byte 80) declares {n} triangles = 84 + 50 × {n} = {84 + 50 * n} "
                     f"bytes, but the file is {size} bytes: truncated or not an STL")


def _stl_ascii_facets(path: Path) -> int | None:
    with open(path, "rb") as fh:
        data = fh.read()
    if len(data) >= 84 and 84 + 50 * struct.unpack_from("<I", data, 80)[0] == len(data):
        return None
    return len(re.findall(rb"\bendfacet\b", data))


def check_off(path: Path) -> tuple[int, int]:
    """The vertex and face counts an OFF header declares, checked against the file length."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(4096)
    tokens = [t for t in _OFF_TOKEN.findall(head) if not t.startswith(b"#")]
    if not tokens or not tokens[0].endswith(b"OFF") or len(tokens) < 3:
        raise InputError(f"{path}: not an OFF file (byte 0: expected 'OFF' and the vertex and face counts)")
    try:
        nv, nf = int(tokens[1]), int(tokens[2])
    except ValueError:
        raise InputError(f"{path}: OFF header counts {tokens[1][:20]!r} {tokens[2][:20]!r} are not integers") from None
    # The shortest vertex row is "0 0 0\n" (6 bytes), the shortest face row "3 0 1 2\n" (8 bytes).
    if nv < 0 or nf < 0 or 6 * nv + 8 * nf > size:
        raise InputError(f"{path}: OFF header declares {nv} vertices and {nf} faces (at least {6 * nv + 8 * nf} "
                         f"bytes), the file is {size} bytes")
    return nv, nf


def check_glb(path: Path) -> None:
    """A GLB's header (bytes 8-11) holds its total length; a truncated file is refused before trimesh parses it."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(12)
    if len(head) < 12 or head[:4] != b"glTF":
        raise InputError(f"{path}: not a GLB file (byte 0: no 'glTF' magic)")
    length = struct.unpack_from("<I", head, 8)[0]
    if length != size:
        raise InputError(f"{path}: GLB header (byte 8) declares {length} bytes, the file is {size} bytes")


def obj_face_problem(path: Path) -> str | None:
    """The first OBJ ``f`` line trimesh cannot use (an index that is not an integer or out of range), if any."""
    with open(path, "rb") as fh:
        lines = fh.read().split(b"\n")
    total = sum(1 for line in lines if line.lstrip().startswith((b"v ", b"v\t")))
    seen = 0
    for number, line in enumerate(lines, start=1):
        words = line.split()
        if words[:1] == [b"v"]:
            seen += 1
        if words[:1] != [b"f"]:
            continue
        if len(words) < 4:
            return f"line {number}: face with {len(words) - 1} vertices (a face needs at least 3)"
        for tok in words[1:]:
            try:
                k = int(tok.split(b"/")[0])
            except ValueError:
                return f"line {number}: face index {tok[:20].decode('latin-1')!r} is not an integer"
            if k == 0 or k > total or k < -seen:
                return f"line {number}: face index {k} is out of range (the file has {total} vertices)"
    return None


def check_triangles(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Face indices within [0, n_vertices) and finite vertices, naming the first bad row."""
    out = (faces < 0) | (faces >= len(vertices))
    if out.any():
        row = int(np.argmax(out.any(axis=1)))
        raise InputError(f"{path}: face row {row + 1}: vertex index {faces[row].tolist()} out of range "
                         f"[0, {len(vertices)})")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        row = int(np.argmax(bad))
        raise nonfinite(path, vertices, bad, f"vertex row {row + 1}")


def degenerate_mask(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Mask of the faces without an area: a repeated vertex index, collinear or coincident corners."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    doubled_area = np.linalg.norm(triangle_normals(vertices[faces]), axis=1)
    longest = np.max([((b - a) ** 2).sum(1), ((c - b) ** 2).sum(1), ((a - c) ** 2).sum(1)], axis=0)
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    return repeated | (doubled_area <= DEGENERATE_AREA * longest)


def merged_mesh(req: ReadRequest, parts: list[tuple[np.ndarray, np.ndarray]], meta: dict[str, str]) -> Dataset:
    """Several parts' meshes (vertices, faces) as one dataset named after the input, in part order."""
    starts = np.cumsum([0] + [len(verts) for verts, _ in parts[:-1]])
    return Dataset(name=req.name, role=req.role, points=np.vstack([verts for verts, _ in parts]),
                   faces=np.vstack([faces + s for (_, faces), s in zip(parts, starts, strict=True)]), meta=meta)


def drop_degenerate(path: Path, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Faces without an area (a repeated vertex index, collinear or coincident corners) removed, and their count."""
    degenerate = degenerate_mask(vertices, faces)
    n = int(degenerate.sum())
    if n == len(faces):
        raise InputError(f"{path}: all {n} facets are degenerate (repeated vertices or zero area)")
    if n:
        log.warning("%s: dropped %d degenerate facets of %d (repeated vertices or zero area)", path, n, len(faces))
    return faces[~degenerate], n


def _declared(path: Path) -> tuple[int | None, int | None]:
    """(vertices, faces) the file itself declares, checked against its length before trimesh is asked."""
    ext = path.suffix.lower()
    if ext == ".ply":
        ply = read_ply(path)
        if ply.faces is None or len(ply.faces.counts) == 0:
            raise InputError(f"{path}: no faces (is it a mesh? set `kind: points` for a point cloud)")
        return len(ply.vertices), int((ply.faces.counts - 2).sum())
    if ext == ".stl":
        check_stl(path)
        return None, _stl_ascii_facets(path)
    if ext == ".off":
        return check_off(path)
    if ext == ".glb":
        check_glb(path)
    if ext == ".obj":
        with open(path, "rb") as fh:
            return None, len(_OBJ_FACE.findall(fh.read()))
    return None, None


def read_mesh(req: ReadRequest) -> Dataset:
    """A triangle mesh through trimesh, with the file's declared sizes checked before and trimesh's result after."""
    import trimesh

    path, process = req.path, req.params.process
    n_vertices, n_faces = _declared(path)
    try:
        mesh = trimesh.load(str(path), force="mesh", process=process)
    except Exception as exc:
        problem = obj_face_problem(path) if path.suffix.lower() == ".obj" else None
        raise InputError(f"{path}: {problem or 'cannot read as a mesh'} ({type(exc).__name__}: {exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"{path}: no triangles found (is it a mesh? set `kind: points` for a point cloud)")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if not process and n_vertices is not None and len(vertices) != n_vertices:
        raise InputError(f"{path}: the file declares {n_vertices} vertices, trimesh read {len(vertices)}")
    if n_faces is not None and len(faces) < n_faces and not process:
        problem = obj_face_problem(path) if path.suffix.lower() == ".obj" else None
        raise InputError(f"{path}: the file declares {n_faces} faces ('f' lines, facets or header count), "
                         f"trimesh read only {len(faces)}" + (f"; {problem}" if problem else ""))
    check_triangles(path, vertices, faces)
    faces, dropped = drop_degenerate(path, vertices, faces)
    if dropped:
        req.report(degenerate_facets_dropped=dropped)
    return Dataset(name=req.name, role=req.role, points=vertices, faces=faces)


class MeshParams(BaseModel):
    """Parameters of the trimesh mesh reader."""

    model_config = ConfigDict(extra="forbid")
    process: bool = Field(False, description="Let trimesh merge duplicate vertices and drop degenerate faces "
                                             "(changes element order: off by default so facets stay traceable).")


def _accepts_mesh(path: Path, kind: str | None) -> bool:
    if kind == "points":
        return False
    if path.suffix.lower() == ".ply" and kind is None:
        return (face_count(path) or 0) > 0
    return True


READER = ReaderSpec(name="trimesh_mesh", version=VERSION, params=MeshParams, read=read_mesh, accepts=_accepts_mesh,
                    extensions=(".obj", ".ply", ".stl", ".off", ".glb", ".gltf"),
                    description="Triangle meshes through trimesh (faces are the elements).")
