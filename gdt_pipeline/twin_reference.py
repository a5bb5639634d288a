"""The composite as the twin store holds it, read back for the next epoch: float32 positions about each set's origin,
the stored uncertainty parameters, the stored scores and states. Every run hands each epoch this reference, whether
the epoch before it ran in the same process or years earlier, so that a twin grown one append at a time is the twin
a single run of the same epochs makes."""

from __future__ import annotations

import numpy as np

from twin_store import ElementSet, TwinStore

from .types import (
    BoxUncertainty,
    Composite,
    CompositeItem,
    Dataset,
    GaussianUncertainty,
    MixtureUncertainty,
)
from .types.arrays import covariance33
from .types.uncertainty import Uncertainty


def _shared(rows: np.ndarray) -> np.ndarray:
    """One row when every element has the same one (a tolerance given once), so the model stays shared and small."""
    return rows[:1] if len(rows) > 1 and bool(np.all(rows == rows[:1])) else rows


def stored_uncertainty(es: ElementSet) -> Uncertainty | None:
    """The uncertainty model a set's stored parameters describe (a stored mixture keeps only its moments: one
    component with them)."""
    if es.uncertainty_model == "none":
        return None
    if es.uncertainty_model == "box":
        assert es.half_widths is not None
        rotation = None if es.rotation is None else _shared(np.asarray(es.rotation, np.float64))
        return BoxUncertainty(_shared(np.asarray(es.half_widths, np.float64)), rotation)
    assert es.covariance is not None
    cov = covariance33(_shared(np.asarray(es.covariance, np.float64)))
    if es.uncertainty_model == "mixture":
        k = len(cov)
        return MixtureUncertainty(np.ones((k, 1)), np.zeros((k, 1, 3)), cov[:, None])
    dofs = None if es.dof is None else np.unique(np.asarray(es.dof, np.float64))
    if dofs is not None and len(dofs) != 1:
        raise ValueError(f"twin set {es.key}: its Student t holds {len(dofs)} degrees of freedom, one is expected")
    return GaussianUncertainty(cov, dof=None if dofs is None else float(dofs[0]))


def _fields(es: ElementSet) -> dict[str, np.ndarray]:
    """The per-element values a reader found, as the twin kept them."""
    found = {"intensity": es.intensity, "color": es.scan_color, "classification": es.classification}
    return {name: np.asarray(values) for name, values in found.items() if values is not None}


def _origin(es: ElementSet, roles: dict[str, str]) -> tuple[str, str, str]:
    """The epoch that brought a set in, its role and the dataset's name; for a set written before the twin kept
    them, from its key (``<epoch>_<name>``, the fusion's) and the epochs' recorded roles."""
    if es.item:
        return es.item["epoch"], es.item["role"], es.item["name"]
    epoch = max((e for e in roles if es.key.startswith(f"{e}_")), key=len, default=None)
    if epoch is None:
        raise ValueError(f"twin set {es.key}: the twin does not say which epoch brought it in")
    return epoch, roles[epoch], es.key[len(epoch) + 1:]


def _f64(values: np.ndarray | None) -> np.ndarray | None:
    return None if values is None else np.asarray(values, np.float64)


def item_from_set(es: ElementSet, roles: dict[str, str]) -> CompositeItem:
    """The composite item a stored set holds."""
    epoch, role, name = _origin(es, roles)
    ds = Dataset(name, role, es.points, faces=es.faces, uncertainty=stored_uncertainty(es), fields=_fields(es),
                 meta=dict(es.identity or {}))
    return CompositeItem(key=es.key, dataset=ds, epoch=epoch, state=es.state, score=_f64(es.score),
                         source_epoch=es.source_epoch, visible=es.visible, p_value=_f64(es.p_value),
                         reason=es.reason, reason_ratio=_f64(es.reason_ratio), area_seen=_f64(es.area_seen),
                         area_removed=_f64(es.area_removed))


def stored_composite(store: TwinStore, epoch_id: str, roles: dict[str, str]) -> Composite:
    """The composite at ``epoch_id`` as the twin stores it, read set by set (``roles``: each epoch's role); the
    retired sets (no element visible) only by name and removed count, so that an append's cost follows what is
    still shown, not the history."""
    items = tuple(item_from_set(es, roles) for es in store.iter_epoch(epoch_id, retired=False))
    return Composite(items, retired=tuple(sorted(store.retired_removed(epoch_id).items())))
