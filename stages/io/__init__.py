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

from gdt_pipeline import ReaderSpec, hookimpl

from . import cad, e57, ifc, las, mesh, points

__all__ = ["gdt_readers"]


@hookimpl
def gdt_readers() -> list[ReaderSpec]:
    """The built-in readers."""
    return [mesh.READER, points.READER, las.READER, e57.READER, ifc.READER, cad.READER]
