"""Readers: meshes through trimesh (OBJ/PLY/STL/OFF/GLB), point clouds (PLY and the XYZ family read here, PCD
through Open3D), airborne/terrestrial LiDAR through laspy (LAS/LAZ) and scanner exchange files through pye57 (E57:
one dataset per scan, with its station). The engine picks one per input by extension and ``accepts``, then checks
what it returns (finite coordinates, not empty), applies the unit scale and settles each dataset's station.
IFC models are read through IfcOpenShell: one mesh per product, its GlobalId, class and name kept (``ifc``).
STEP/IGES CAD through cascadio (OpenCASCADE): one mesh per top-level part, in metres, part name kept (``cad``).

No parser is trusted with a bad file: each reader checks the file's declared sizes against its length before
anything is allocated and checks what the parser returned against the file's own counts (``ply``, ``mesh``,
``points``, ``las``), so a file the parser could not read is an error naming the place, never data.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from gdt_pipeline import Dataset, InputError, ReaderSpec, ReadRequest, hookimpl

from .cad import CAD_VERSION, CadParams, accepts_cad, read_cad
from .e57 import E57Params, read_e57
from .ifc import IFC_VERSION, IfcParams, read_ifc
from .las import read_las
from .mesh import read_mesh
from .ply_header import face_count
from .points import read_point_file

# 1.1.0: bad files (counts the data does not hold, tokens that are not numbers, truncated binaries, degenerate
# facets) are errors or dropped instead of becoming data. 1.2.0: LAS/LAZ carry intensity and colour.
VERSION = "1.2.0"


def ply_face_count(path: Path) -> int | None:
    """Number of faces a PLY header declares (None when the file is not a readable PLY)."""
    return face_count(path)


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


class PointsParams(BaseModel):
    """Parameters of the Open3D point-cloud reader."""

    model_config = ConfigDict(extra="forbid")


def _accepts_points(path: Path, kind: str | None) -> bool:
    if kind == "mesh":
        return False
    if path.suffix.lower() == ".ply" and kind is None:
        # An unreadable header (None) is taken too, so that the error names what is wrong with it.
        return ply_face_count(path) in (0, None)
    return True


def _read_points(req: ReadRequest) -> Dataset:
    return Dataset(name=req.name, role=req.role, points=read_point_file(req.path))


class LasParams(BaseModel):
    """Parameters of the laspy LAS/LAZ reader."""

    model_config = ConfigDict(extra="forbid")
    classes: list[int] | None = Field(None, description="Keep only points of these ASPRS classes (e.g. [2] ground).")
    attributes: list[Literal["intensity", "color"]] = Field(
        ["intensity", "color"], description="Per-point values to carry into the twin when the file has them "
                                            "(gdt:intensity, gdt:scanColor); [] for coordinates only.")


def _read_las(req: ReadRequest) -> Dataset:
    pts, fields = read_las(req.path, req.params.classes, tuple(req.params.attributes))
    if len(pts) == 0:
        raise InputError(f"{req.path}: no points (after the class filter {req.params.classes})")
    return Dataset(name=req.name, role=req.role, points=pts, fields=fields)


@hookimpl
def gdt_readers() -> list[ReaderSpec]:
    """The built-in readers."""
    return [
        ReaderSpec(name="trimesh_mesh", version=VERSION, params=MeshParams, read=read_mesh, accepts=_accepts_mesh,
                   extensions=(".obj", ".ply", ".stl", ".off", ".glb", ".gltf"),
                   description="Triangle meshes through trimesh (faces are the elements)."),
        ReaderSpec(name="open3d_points", version=VERSION, params=PointsParams, read=_read_points,
                   accepts=_accepts_points, extensions=(".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts"),
                   description="Point clouds: PLY and XYZ/XYZN/XYZRGB/PTS read and checked here, PCD through Open3D."),
        ReaderSpec(name="laspy_points", version=VERSION, params=LasParams, read=_read_las, extensions=(".las", ".laz"),
                   description="LAS/LAZ LiDAR point clouds through laspy (lazrs backend)."),
        ReaderSpec(name="pye57_scans", version=VERSION, params=E57Params, read=read_e57, extensions=(".e57",),
                   description="E57 scans through pye57: one dataset per scan, its station from the header, "
                               "intensity and colour."),
        ReaderSpec(name="ifcopenshell_ifc", version=IFC_VERSION, params=IfcParams, read=read_ifc, extensions=(".ifc",),
                   description="IFC models through IfcOpenShell: one mesh per product, GlobalId and class kept."),
        ReaderSpec(name="cascadio_cad", version=CAD_VERSION, params=CadParams, read=read_cad, accepts=accepts_cad,
                   extensions=(".step", ".stp", ".igs", ".iges"),
                   description="STEP/IGES B-rep CAD through cascadio (OpenCASCADE), tessellated to `tolerance` "
                               "metres: one mesh per top-level part named by its product (IGES: one mesh), in "
                               "metres whatever the file's unit."),
    ]
