"""The engine's composite as the twin store's element sets (one per item, with its uncertainty, states and scores; the
store knows numpy and pxr only), and, read back from a twin, which identified parts (IFC elements, named CAD parts)
an epoch removed."""

from __future__ import annotations

from typing import Any

import numpy as np

from twin_store import ElementSet, SetsOnDemand, TwinStore

from .types import ChangeState, Composite, CompositeItem, Dataset


def composite_to_elements(composite: Composite) -> SetsOnDemand:
    """One element set per composite item, with its uncertainty, states and scores, each made as the writer reads it
    (its packed covariances and float32 columns are 100 B a point: one set's at a time, not the epoch's)."""
    items = composite.items
    return SetsOnDemand([it.key for it in items], lambda i: _element_set(items[i]))


def _element_set(it: CompositeItem) -> ElementSet:
    """The element set of one composite item."""
    ds = it.dataset
    n = ds.n_elements
    unc = ds.uncertainty
    arrays: dict[str, np.ndarray | None] = {"covariance": None, "half_widths": None, "rotation": None}
    if unc is not None:
        arrays.update(unc.stored(n))
    return ElementSet(key=it.key, kind=ds.kind, points=ds.points, faces=ds.faces,
                      uncertainty_model="none" if unc is None else unc.model, **arrays,
                      uncertainty_summary=np.full(n, np.nan) if unc is None else np.asarray(unc.summary(n)),
                      state=it.state, score=it.score.astype(np.float32), source_epoch=it.source_epoch,
                      visible=it.visible,
                      p_value=None if it.p_value is None else it.p_value.astype(np.float32),
                      reason=it.reason, reason_ratio=it.reason_ratio.astype(np.float32),
                      area_seen=_f32(it.area_seen), area_removed=_f32(it.area_removed),
                      intensity=_f32(ds.fields.get("intensity")), scan_color=_f32(ds.fields.get("color")),
                      identity=dict(ds.meta) or None, classification=_classes(ds),
                      item={"epoch": it.epoch, "role": ds.role, "name": ds.name})


def _classes(ds: Dataset) -> np.ndarray | None:
    """The LAS classes of a dataset's points, as uint8 (None when its reader gave none)."""
    values = ds.fields.get("classification")
    return None if values is None else np.asarray(values).astype(np.uint8)


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
