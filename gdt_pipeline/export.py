"""Export the twin at an epoch: flat USD, USDZ, PLY (one file per element set), OBJ, LAS/LAZ with the per-point
values (``export_las``), or a PNG picture.

PLY and OBJ carry the composite only (hidden elements are left out) with change colours; USD keeps everything,
the history included. Point sets go through Open3D (PLY with double coordinates, so georeferenced clouds keep their
precision); meshes through trimesh.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from twin_store import STATE_COLORS, ElementSet, TwinStore

from .errors import GdtError

FORMATS = ("usda", "usdc", "usdz", "ply", "obj", "png", "las", "laz")


def _colors(es: ElementSet) -> np.ndarray:
    return np.asarray(es.display_color if es.display_color is not None else STATE_COLORS[es.state], dtype=np.float64)


def export_ply(elements: list[ElementSet], out_dir: Path) -> list[Path]:
    """One PLY per element set with its visible elements: meshes with face colours, points with vertex colours."""
    import open3d as o3d
    import trimesh

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for es in elements:
        vis = np.asarray(es.visible, dtype=bool)
        if not vis.any():
            continue
        path = out_dir / f"{es.key}.ply"
        tmp = out_dir / f".{es.key}.tmp-{os.getpid()}.ply"
        if es.kind == "mesh":
            mesh = trimesh.Trimesh(es.points, es.faces[vis], process=False)
            mesh.visual.face_colors = np.c_[np.round(_colors(es)[vis] * 255), np.full(vis.sum(), 255)].astype(np.uint8)
            tmp.write_bytes(mesh.export(file_type="ply"))
        else:
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(es.points[vis]))
            pcd.colors = o3d.utility.Vector3dVector(_colors(es)[vis])
            if not o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False):
                raise GdtError(f"could not write {tmp}")
        os.replace(tmp, path)
        written.append(path)
    return written


def export_obj(elements: list[ElementSet], out: Path) -> Path:
    """One OBJ with an object per element set: visible facets of meshes, visible points as vertices."""
    import trimesh

    scene = trimesh.Scene()
    for es in elements:
        vis = np.asarray(es.visible, dtype=bool)
        if not vis.any():
            continue
        if es.kind == "mesh":
            scene.add_geometry(trimesh.Trimesh(es.points, es.faces[vis], process=False), geom_name=es.key)
        else:
            scene.add_geometry(trimesh.PointCloud(es.points[vis]), geom_name=es.key)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp-{os.getpid()}.obj")
    tmp.write_text(trimesh.exchange.obj.export_obj(scene, include_normals=False, include_texture=False,
                                                   include_color=False))
    os.replace(tmp, out)
    return out


def export_twin(store: TwinStore, epoch: str, out: Path, fmt: str | None = None) -> list[Path]:
    """Export the twin at ``epoch`` to ``out`` in ``fmt`` (default: from the file extension)."""
    fmt = (fmt or out.suffix.lstrip(".")).lower()
    if fmt not in FORMATS:
        raise GdtError(f"unknown export format {fmt!r} for {out} (choose one of: {', '.join(FORMATS)})")
    if fmt in ("usda", "usdc"):
        target = out if out.suffix.lower() == f".{fmt}" else out.with_suffix(f".{fmt}")
        return [store.flatten(epoch, target)]
    if fmt == "usdz":
        return [store.export_usdz(epoch, out if out.suffix.lower() == ".usdz" else out.with_suffix(".usdz"))]
    if fmt == "png":
        import tempfile

        from .render import render_file

        with tempfile.TemporaryDirectory() as tmp:
            flat = store.flatten(epoch, Path(tmp) / "flat.usdc")
            return [render_file(flat, out if out.suffix.lower() == ".png" else out.with_suffix(".png"))]
    elements = store.read_epoch(epoch)
    if fmt in ("las", "laz"):
        from .export_las import export_las

        folder = out.with_suffix("") if out.suffix.lower() in (".las", ".laz") else out
        return export_las(elements, folder, store.meters_per_unit(), compressed=fmt == "laz")
    if fmt == "obj":
        return [export_obj(elements, out if out.suffix.lower() == ".obj" else out.with_suffix(".obj"))]
    return export_ply(elements, out.with_suffix("") if out.suffix.lower() == ".ply" else out)
