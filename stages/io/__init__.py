"""Readers: meshes through trimesh (OBJ/PLY/STL/OFF/GLB), point clouds through Open3D (PLY/PCD/XYZ/PTS) and
airborne/terrestrial LiDAR through laspy (LAS/LAZ). The engine picks one per input by extension and ``accepts``,
then checks what it returns (finite coordinates, not empty) and applies the unit scale."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gdt_pipeline import Dataset, InputError, ReaderSpec, ReadRequest, hookimpl

VERSION = "1.0.0"
_FACE_RE = re.compile(rb"^element\s+face\s+(\d+)", re.MULTILINE)


def ply_face_count(path: Path) -> int | None:
    """Number of faces a PLY header declares (None when the file is not a readable PLY)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
    except OSError:
        return None
    if not head.startswith(b"ply"):
        return None
    header = head.split(b"end_header", 1)[0]
    m = _FACE_RE.search(header)
    return int(m.group(1)) if m else 0


class MeshParams(BaseModel):
    """Parameters of the trimesh mesh reader."""

    model_config = ConfigDict(extra="forbid")
    process: bool = Field(False, description="Let trimesh merge duplicate vertices and drop degenerate faces "
                                             "(changes element order: off by default so facets stay traceable).")


def _accepts_mesh(path: Path, kind: str | None) -> bool:
    if kind == "points":
        return False
    if path.suffix.lower() == ".ply" and kind is None:
        return (ply_face_count(path) or 0) > 0
    return True


def _read_mesh(req: ReadRequest) -> Dataset:
    import trimesh

    try:
        mesh = trimesh.load(str(req.path), force="mesh", process=req.params.process)
    except Exception as exc:
        raise InputError(f"{req.path}: cannot read as a mesh ({type(exc).__name__}: {exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"{req.path}: no triangles found (is it a mesh? set `kind: points` for a point cloud)")
    return Dataset(name=req.name, role=req.role, points=np.asarray(mesh.vertices, dtype=np.float64),
                   faces=np.asarray(mesh.faces, dtype=np.int64))


class PointsParams(BaseModel):
    """Parameters of the Open3D point-cloud reader."""

    model_config = ConfigDict(extra="forbid")


def _accepts_points(path: Path, kind: str | None) -> bool:
    if kind == "mesh":
        return False
    if path.suffix.lower() == ".ply" and kind is None:
        return ply_face_count(path) == 0
    return True


def _read_points(req: ReadRequest) -> Dataset:
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    # NaN points are kept on purpose so that the engine reports them instead of silently dropping data.
    pcd = o3d.io.read_point_cloud(str(req.path), remove_nan_points=False, remove_infinite_points=False)
    pts = np.asarray(pcd.points, dtype=np.float64)
    if len(pts) == 0:
        raise InputError(f"{req.path}: no points read (the file is empty, truncated or not a point cloud)")
    return Dataset(name=req.name, role=req.role, points=pts)


class LasParams(BaseModel):
    """Parameters of the laspy LAS/LAZ reader."""

    model_config = ConfigDict(extra="forbid")
    classes: list[int] | None = Field(None, description="Keep only points of these ASPRS classes (e.g. [2] ground).")


def _read_las(req: ReadRequest) -> Dataset:
    import laspy

    try:
        las = laspy.read(str(req.path))
    except Exception as exc:
        raise InputError(f"{req.path}: cannot read LAS/LAZ ({type(exc).__name__}: {exc})") from exc
    pts = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]).astype(np.float64)
    if req.params.classes is not None:
        pts = pts[np.isin(np.asarray(las.classification), req.params.classes)]
    if len(pts) == 0:
        raise InputError(f"{req.path}: no points (after the class filter {req.params.classes})")
    return Dataset(name=req.name, role=req.role, points=pts)


@hookimpl
def gdt_readers() -> list[ReaderSpec]:
    """The built-in readers."""
    return [
        ReaderSpec(name="trimesh_mesh", version=VERSION, params=MeshParams, read=_read_mesh, accepts=_accepts_mesh,
                   extensions=(".obj", ".ply", ".stl", ".off", ".glb", ".gltf"),
                   description="Triangle meshes through trimesh (faces are the elements)."),
        ReaderSpec(name="open3d_points", version=VERSION, params=PointsParams, read=_read_points,
                   accepts=_accepts_points, extensions=(".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts"),
                   description="Point clouds through Open3D."),
        ReaderSpec(name="laspy_points", version=VERSION, params=LasParams, read=_read_las, extensions=(".las", ".laz"),
                   description="LAS/LAZ LiDAR point clouds through laspy (lazrs backend)."),
    ]
