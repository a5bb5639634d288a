"""IFC (BIM) models through IfcOpenShell: one triangle-mesh dataset per product, named ``<class>_<Name>``, that
keeps the product's GlobalId, class and name in ``meta`` (written on its prim, so ``gdt log`` can name a removed
wall by its GlobalId).

The file is checked before IfcOpenShell parses it: IfcOpenShell opens a STEP file cut short without complaint and
returns the entities it got that far, so a truncated model would become a twin missing half its walls. IfcOpenShell's
geometry iterator tessellates the products in world coordinates and in metres whatever the file's length unit
(millimetres, feet, ...): the reader says so (``units`` note, the file's own unit kept as
``ifc_file_unit_m``) and the engine scales from metres.
"""

from __future__ import annotations

import logging
import multiprocessing
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gdt_pipeline import Dataset, InputError, ReaderSpec, ReadRequest

from .mesh import degenerate_mask, merged_mesh
from .step_file import check_spf

log = logging.getLogger(__name__)

IFC_VERSION = "1.0.0"
INSTALL_HINT = "reading IFC needs ifcopenshell: pip install 'gdt-pipeline[bim]'"
# GlobalIds listed by name in the provenance; past this only their count (a model may skip thousands of annotations)
MAX_LISTED = 20


class IfcParams(BaseModel):
    """Parameters of the IfcOpenShell IFC reader."""

    model_config = ConfigDict(extra="forbid")
    classes: list[str] | None = Field(None, description="Keep only products of these IFC classes and their subtypes "
                                                        "(e.g. [IfcWall, IfcSlab]); default every product with a "
                                                        "body representation.")
    exclude: list[str] = Field(["IfcSpace", "IfcOpeningElement"],
                               description="Leave out products of these classes and their subtypes (spaces and "
                                           "openings are volumes, not surfaces anyone scans).")
    merge: bool = Field(False, description="One dataset for the whole model instead of one per product (a large "
                                           "model as one set; the products' identities are lost).")


def open_ifc(path: Path) -> Any:
    """The parsed model (an ``ifcopenshell.file``), after :func:`check_spf`; a parse failure is an InputError."""
    try:
        import ifcopenshell
    except ImportError:
        raise InputError(INSTALL_HINT) from None
    check_spf(path)
    try:
        model = ifcopenshell.open(str(path))
    except (ifcopenshell.Error, RuntimeError, ValueError) as exc:
        raise InputError(f"{path}: cannot parse the IFC file ({type(exc).__name__}: {exc})") from exc
    if not model.schema:
        raise InputError(f"{path}: the IFC header names no schema (FILE_SCHEMA)")
    return model


def _of_classes(model: Any, names: list[str], what: str) -> set[int]:
    """Step ids of the instances of ``names`` and their subtypes; an unknown class is an error naming it."""
    ids: set[int] = set()
    for name in names:
        try:
            ids.update(inst.id() for inst in model.by_type(name))
        except RuntimeError:
            raise InputError(f"{what}: {name!r} is not an entity of the schema {model.schema}") from None
    return ids


def select_products(model: Any, params: IfcParams) -> list[Any]:
    """The products to read: with a representation, of ``classes`` (all by default) and not of ``exclude``, in
    GlobalId order."""
    keep = None if params.classes is None else _of_classes(model, params.classes, "classes")
    drop = _of_classes(model, params.exclude, "exclude")
    products = [p for p in model.by_type("IfcProduct") if p.Representation is not None
                and p.id() not in drop and (keep is None or p.id() in keep)]
    # GlobalId order, not file order: exporters renumber step ids on every save, GlobalIds persist, so a re-saved
    # model gives the same twin
    return sorted(products, key=lambda p: p.GlobalId)


def tessellate(model: Any, products: list[Any]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per product step id, its triangles in world coordinates and metres: (vertices (V,3), faces (F,3))."""
    import ifcopenshell.geom

    settings = ifcopenshell.geom.settings()
    settings.set("use-world-coords", True)
    iterator = ifcopenshell.geom.iterator(settings, model, multiprocessing.cpu_count(), include=products)
    out = {}
    for shape in iterator:  # the threads finish in any order: the caller orders by product
        geometry = shape.geometry
        verts = np.asarray(geometry.verts, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(geometry.faces, dtype=np.int64).reshape(-1, 3)
        out[shape.id] = (verts, faces)
    return out


def file_unit_m(model: Any) -> float:
    """The file's own length unit in metres (0.001 for millimetres); the tessellation is in metres regardless."""
    import ifcopenshell.util.unit

    return float(ifcopenshell.util.unit.calculate_unit_scale(model))


def _listed(global_ids: list[str]) -> list[str]:
    return global_ids[:MAX_LISTED] + ([f"... {len(global_ids) - MAX_LISTED} more"]
                                      if len(global_ids) > MAX_LISTED else [])


def _product_mesh(path: Path, product: Any, shape: tuple[np.ndarray, np.ndarray] | None
                  ) -> tuple[np.ndarray, np.ndarray, int] | None:
    """A product's vertices, its facets with area and how many were dropped; None when it has no facet with area."""
    if shape is None or not len(shape[1]):
        return None
    verts, faces = shape
    if not np.isfinite(verts).all():
        raise InputError(f"{path}: {product.is_a()} {product.GlobalId}: the tessellation has NaN or infinite "
                         f"coordinates")
    bad = degenerate_mask(verts, faces)
    if bad.all():  # a product without a surface, skipped like one without geometry
        return None
    return verts, faces[~bad], int(bad.sum())


def read_ifc(req: ReadRequest) -> list[Dataset] | Dataset:
    """One dataset per IFC product with a surface (GlobalId, class and name in ``meta``), or one for the whole model
    with ``merge``; products without triangles are skipped and reported."""
    model = open_ifc(req.path)
    products = select_products(model, req.params)
    if not products:
        raise InputError(f"{req.path}: no product with a representation (classes {req.params.classes}, "
                         f"exclude {req.params.exclude})")
    shapes = tessellate(model, products)
    parts, skipped, dropped = [], [], 0
    for product in products:
        mesh = _product_mesh(req.path, product, shapes.get(product.id()))
        if mesh is None:
            skipped.append(product.GlobalId)
            continue
        verts, faces, n = mesh
        dropped += n
        name, ifc_class = product.Name or "", product.is_a()
        parts.append(Dataset(name=f"{ifc_class}_{name or product.GlobalId}", role=req.role, points=verts,
                             faces=faces, meta={"name": name, "global_id": product.GlobalId, "ifc_class": ifc_class,
                                                "ifc_file_schema": model.schema}))
    req.report(units="m", ifc_file_unit_m=file_unit_m(model), ifc_schema=model.schema, products=len(parts),
               degenerate_facets_dropped=dropped,
               skipped_without_triangles=len(skipped), **({"skipped": _listed(skipped)} if skipped else {}))
    if skipped or dropped:
        log.warning("%s: %d products without triangles skipped (first: %s); %d degenerate facets dropped", req.path,
                    len(skipped), skipped[:5], dropped)
    if not parts:
        raise InputError(f"{req.path}: none of the {len(products)} products has triangles (body geometry)")
    if req.params.merge:
        return merged_mesh(req, [(ds.points, ds.faces) for ds in parts],
                           {"ifc_file_schema": model.schema, "products": str(len(parts))})
    return parts





READER = ReaderSpec(name="ifcopenshell_ifc", version=IFC_VERSION, params=IfcParams, read=read_ifc,
                    extensions=(".ifc",),
                    description="IFC models through IfcOpenShell: one mesh per product, GlobalId and class kept.")
