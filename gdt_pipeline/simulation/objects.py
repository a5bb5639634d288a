"""The objects of the test scene (a small cuboid, two identical frustums and a larger cuboid that appears later) and
how a generated scene writes its objects as OBJ files."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def frustum(base: float, top: float, height: float):  # -> trimesh.Trimesh
    """A square frustum standing on z=0, as the convex hull of its eight corners (watertight, triangulated)."""
    import trimesh

    b, t = base / 2, top / 2
    corners = np.array([[-b, -b, 0], [b, -b, 0], [b, b, 0], [-b, b, 0],
                        [-t, -t, height], [t, -t, height], [t, t, height], [-t, t, height]], dtype=np.float64)
    return trimesh.convex.convex_hull(corners)


def cuboid(extents: tuple[float, float, float]):  # -> trimesh.Trimesh
    """A box standing on z=0."""
    import trimesh

    box = trimesh.creation.box(extents=extents)
    box.apply_translation((0, 0, extents[2] / 2))
    return box


def scene_objects() -> dict[str, tuple[object, bool]]:
    """The objects of the test scene, in metres: name -> (mesh, present in the CAD of E0)."""
    objects = {
        "small_cuboid": (cuboid((0.30, 0.20, 0.15)), (-0.45, -0.40), True),
        "frustum_a": (frustum(0.30, 0.15, 0.25), (0.45, -0.40), True),
        "frustum_b": (frustum(0.30, 0.15, 0.25), (0.45, 0.45), True),
        "large_cuboid": (cuboid((0.50, 0.35, 0.30)), (-0.40, 0.45), False),
    }
    out = {}
    for name, (mesh, (x, y), in_cad) in objects.items():
        mesh.apply_translation((x, y, 0.0))
        out[name] = (mesh, in_cad)
    return out


def write_objects(root: Path, objects: dict[str, tuple[object, bool]]) -> list[Path]:
    """Write each object as ``cad_<name>.obj`` (in the CAD) or ``truth_<name>.obj`` (only in reality); the CAD paths."""
    cad = []
    for name, (mesh, in_cad) in objects.items():
        path = root / (f"cad_{name}.obj" if in_cad else f"truth_{name}.obj")
        path.write_text(mesh.export(file_type="obj", include_normals=False, include_texture=False))
        if in_cad:
            cad.append(path)
    return cad
