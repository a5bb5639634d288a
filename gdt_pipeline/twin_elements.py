"""The engine's composite as the twin store's element sets (one per item, with its uncertainty, states and scores; the
store knows numpy and pxr only), and, read back from a twin, which identified parts (IFC elements, named CAD parts)
an epoch removed."""

from __future__ import annotations

from typing import Any

import numpy as np

from twin_store import ElementSet, RowsOnDemand, SetsOnDemand, TwinStore

from .types import ChangeState, Composite, CompositeItem, Dataset
from .types.arrays import MappedRows, rows_copy


def composite_to_elements(composite: Composite) -> SetsOnDemand:
    """One element set per composite item, with its uncertainty, states and scores, each made as the writer reads it
    (its packed covariances and float32 columns are 100 B a point: one set's at a time, not the epoch's); a point
    set's made a run of rows at a time (``RowsOnDemand``), so a large set written in parts holds one part's."""
    items = composite.items
    return SetsOnDemand([it.key for it in items], lambda i: _set_source(items[i]))


def _set_source(it: CompositeItem) -> ElementSet | RowsOnDemand:
    """A mesh item's element set, or a point item's rows on demand."""
    ds = it.dataset
    if ds.faces is not None:
        return _element_set(it, slice(None))
    return RowsOnDemand(key=it.key, points=ds.points, state=it.state, visible=it.visible,
                        identity=dict(ds.meta) or None, item=_item(it),
                        make=lambda start, stop: _element_set(it, slice(start, stop)))


def _element_set(it: CompositeItem, rows: slice) -> ElementSet:
    """The element set of the elements ``rows`` of one composite item (of a point item: a run of its points)."""
    ds = it.dataset
    points = ds.points if ds.faces is not None else _point_rows(ds.points, rows)
    n = ds.n_elements if ds.faces is not None else len(points)
    unc = ds.uncertainty
    if unc is not None and rows != slice(None):
        unc = unc.take(rows)
    arrays: dict[str, np.ndarray | None] = {"covariance": None, "half_widths": None, "rotation": None}
    if unc is not None:
        arrays.update(unc.stored(n))
    return ElementSet(key=it.key, kind=ds.kind, points=points, faces=ds.faces,
                      uncertainty_model="none" if unc is None else unc.model, **arrays,
                      uncertainty_summary=np.full(n, np.nan) if unc is None else np.asarray(unc.summary(n)),
                      state=it.state[rows], score=it.score[rows].astype(np.float32),
                      source_epoch=it.source_epoch[rows], visible=it.visible[rows],
                      p_value=None if it.p_value is None else it.p_value[rows].astype(np.float32),
                      reason=_rows(it.reason, rows), reason_ratio=_f32(_rows(it.reason_ratio, rows)),
                      area_seen=_f32(_rows(it.area_seen, rows)), area_removed=_f32(_rows(it.area_removed, rows)),
                      intensity=_f32(_rows(ds.fields.get("intensity"), rows)),
                      scan_color=_f32(_rows(ds.fields.get("color"), rows)),
                      identity=dict(ds.meta) or None, classification=_classes(ds, rows), item=_item(it))


def _item(it: CompositeItem) -> dict[str, str]:
    """What brought the item's set in: its epoch, role and dataset name."""
    return {"epoch": it.epoch, "role": it.dataset.role, "name": it.dataset.name}


def _point_rows(points: np.ndarray, rows: slice) -> np.ndarray:
    """A run of a point set's rows: of points kept in a scratch file, a copy whose pages the process lets go of
    (a view of the map would hold every page the writer touched, the whole scan by the last part)."""
    if not isinstance(points, MappedRows):
        return points[rows]
    start, stop, step = rows.indices(len(points))
    return rows_copy(points, start, stop) if step == 1 else np.array(points[rows])


def _rows(values: np.ndarray | None, rows: slice) -> np.ndarray | None:
    return None if values is None else values[rows]


def _classes(ds: Dataset, rows: slice) -> np.ndarray | None:
    """The LAS classes of the dataset's elements ``rows``, as uint8 (None when its reader gave none)."""
    values = ds.fields.get("classification")
    return None if values is None else np.asarray(values)[rows].astype(np.uint8)


def _f32(values: np.ndarray | None) -> np.ndarray | None:
    return None if values is None else values.astype(np.float32)


def identified_changes(store: TwinStore, epoch_ids: list[str]) -> dict[str, list[dict[str, Any]]]:
    """Per epoch, the sets with an identity outside the twin (an IFC element, a named CAD part) that lost elements in
    it: their key, identity, and how many of the elements visible before were removed (hidden, state removed).
    Only the identified sets' state and visibility are read (``TwinStore.iter_sets``), never their geometry."""
    out: dict[str, list[dict[str, Any]]] = {}
    for epoch_id in epoch_ids[1:]:
        for es in store.iter_sets(epoch_id):
            identity = es.identity
            was_visible = es.field_before("visible") if identity else None
            if was_visible is None or not was_visible.any():
                continue
            gone = (es.field("state") == ChangeState.REMOVED) & ~es.field("visible") & was_visible
            if gone.any():
                out.setdefault(epoch_id, []).append({"key": es.key, "identity": identity, "kind": es.kind,
                                                     "removed": int(gone.sum()), "of": int(was_visible.sum())})
    return out


def identity_label(identity: dict[str, str]) -> str:
    """How a set is named to people: its class, name and GlobalId (IFC) or part name, as known."""
    parts = [identity.get("ifc_class", ""), repr(identity["name"]) if identity.get("name") else "",
             f"GlobalId {identity['global_id']}" if identity.get("global_id") else ""]
    return " ".join(p for p in parts if p) or ", ".join(f"{k}={v}" for k, v in identity.items())
