"""Export the twin at an epoch: flat USD, USDZ, PLY (one file per element set, ``export_ply``), OBJ, LAS/LAZ
(``export_las``), or a PNG picture.

PLY and LAS/LAZ carry the per-element values as scalar fields, and a scope: the composite (every visible element at
the epoch) or only the visible elements the epoch itself supplied. OBJ carries the composite, geometry only; USD keeps
everything, the history included.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from twin_store import ElementSet, TwinStore

from .errors import GdtError
from .export_ply import export_ply
from .export_values import written_in_place

FORMATS = ("usda", "usdc", "usdz", "ply", "obj", "png", "las", "laz")
SCOPES = ("composite", "epoch")
SCOPED_FORMATS = ("ply", "las", "laz")  # the exports that carry source_epoch, so a file of one epoch's part reads right


def supplied_by(elements: list[ElementSet], epoch_index: int) -> list[ElementSet]:
    """The sets with only the visible elements the epoch at ``epoch_index`` (its place in the twin) supplied left."""
    return [dataclasses.replace(es, visible=np.asarray(es.visible, dtype=bool)
                                & (np.asarray(es.source_epoch) == epoch_index)) for es in elements]


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
    with written_in_place(out) as tmp:
        tmp.write_text(trimesh.exchange.obj.export_obj(scene, include_normals=False, include_texture=False,
                                                       include_color=False))
    return out


def export_twin(store: TwinStore, epoch: str, out: Path, fmt: str | None = None, scope: str = "composite"
                ) -> list[Path]:
    """Export the twin at ``epoch`` to ``out`` in ``fmt`` (default: from the file extension) for ``scope``."""
    fmt = (fmt or out.suffix.lstrip(".")).lower()
    if fmt not in FORMATS:
        raise GdtError(f"unknown export format {fmt!r} for {out} (choose one of: {', '.join(FORMATS)})")
    if scope not in SCOPES:
        raise GdtError(f"unknown export scope {scope!r} (choose one of: {', '.join(SCOPES)})")
    if scope != "composite" and fmt not in SCOPED_FORMATS:
        raise GdtError(f"the export scope {scope!r} applies to {', '.join(SCOPED_FORMATS)} only, not {fmt}")
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
    if scope == "epoch":
        # source_epoch holds the epoch's index in the run, which is its place in the twin (a run writes all its epochs)
        elements = supplied_by(elements, store.epochs().index(epoch))
    if fmt in ("las", "laz"):
        from .export_las import export_las

        folder = out.with_suffix("") if out.suffix.lower() in (".las", ".laz") else out
        return export_las(elements, folder, store.meters_per_unit(), compressed=fmt == "laz")
    if fmt == "obj":
        return [export_obj(elements, out if out.suffix.lower() == ".obj" else out.with_suffix(".obj"))]
    return export_ply(elements, out.with_suffix("") if out.suffix.lower() == ".ply" else out, store.meters_per_unit())
