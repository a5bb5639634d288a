"""Cutting an epoch's slots down to one tile and its halo, and taking subsets of elements and candidates.

A reference item keeps its points inside the halo box and its facets whose bounding box meets it, so every element
a stage can reach from the tile's core within the halo is there; crops remember which elements they kept (sorted
global indices), which is how results are mapped back.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from ..types import Change, Composite, CompositeItem, Correspondences, Dataset, RegionOfView, Scores

IndexMap = Callable[[np.ndarray], np.ndarray]


def take_dataset(ds: Dataset, elements: np.ndarray) -> Dataset:
    """The elements ``elements`` (sorted) of a dataset: its points, or its facets on the vertices they use."""
    unc = None if ds.uncertainty is None else ds.uncertainty.take(elements)
    if ds.faces is None:
        return dataclasses.replace(ds, points=ds.points[elements], uncertainty=unc, fields=ds.take_fields(elements))
    faces = ds.faces[elements]
    used, local = np.unique(faces, return_inverse=True)
    return dataclasses.replace(ds, points=ds.points[used], faces=local.reshape(-1, 3), uncertainty=unc,
                               fields=ds.take_fields(elements))


def in_box(ds: Dataset, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Sorted indices of the elements that reach into the box: points inside it, facets whose bounding box meets it."""
    if ds.faces is None:
        return np.flatnonzero(np.all((ds.points >= lower) & (ds.points <= upper), axis=1))
    tri = ds.points[ds.faces]
    return np.flatnonzero(np.all((tri.max(axis=1) >= lower) & (tri.min(axis=1) <= upper), axis=1))


def take_item(item: CompositeItem, elements: np.ndarray) -> CompositeItem:
    """The elements ``elements`` of a composite item, with every per-element array."""
    def sub(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else a[elements]

    return dataclasses.replace(item, dataset=take_dataset(item.dataset, elements), state=item.state[elements],
                               score=item.score[elements], source_epoch=item.source_epoch[elements],
                               visible=item.visible[elements], p_value=sub(item.p_value), reason=sub(item.reason),
                               reason_ratio=sub(item.reason_ratio), area_seen=sub(item.area_seen),
                               area_removed=sub(item.area_removed))


def crop_composite(composite: Composite, lower: np.ndarray, upper: np.ndarray,
                   extra: dict[int, np.ndarray] | None = None,
                   finders: Sequence[Callable[[np.ndarray, np.ndarray], np.ndarray] | None] | None = None
                   ) -> tuple[Composite, list[np.ndarray]]:
    """The composite cut to a box (plus the elements ``extra`` names per item), and per item the elements kept.
    ``finders[i](lower, upper)``, when given, finds item i's elements in a box faster than a scan (``CellIndex``).
    Every item stays, empty or not, so item numbers mean the same in the crop; segments are left out."""
    keeps, items = [], []
    for i, item in enumerate(composite.items):
        finder = finders[i] if finders is not None else None
        keep = finder(lower, upper) if finder is not None else in_box(item.dataset, lower, upper)
        if extra and i in extra and len(extra[i]):
            keep = np.union1d(keep, extra[i])
        keeps.append(keep)
        items.append(item if len(keep) == item.dataset.n_elements else take_item(item, keep))
    return Composite(items=tuple(items)), keeps


def crop_rov(rov: RegionOfView, keeps: Sequence[np.ndarray], keys: Sequence[str]) -> RegionOfView:
    """The region of view with its per-element judgements of the reference cut like the reference."""
    by_key = dict(zip(keys, keeps, strict=True))
    return dataclasses.replace(rov, views={k: v.take(by_key[k]) if k in by_key else v for k, v in rov.views.items()})


def lookup(sorted_ids: np.ndarray) -> IndexMap:
    """Global → local index through a sorted array of kept global indices (−1 where not kept)."""
    def local(ids: np.ndarray) -> np.ndarray:
        pos = np.minimum(np.searchsorted(sorted_ids, ids), max(len(sorted_ids) - 1, 0))
        hit = (sorted_ids[pos] == ids) if len(sorted_ids) else np.zeros(len(ids), bool)
        return np.where(hit, pos, -1)

    return local


def take_candidates(corr: Correspondences, keep: np.ndarray, element_of: IndexMap,
                    ref_element_of: Sequence[IndexMap], n_elements: int) -> Correspondences:
    """The candidates ``keep`` (a mask) with their query and reference elements renumbered by the maps, and only
    the reference rows they use."""
    sub = corr.take(np.flatnonzero(keep))
    item = sub.ref_item
    ref_element = sub.ref_element.astype(np.int64)  # the epoch's numbers may not fit the tile's int32
    for i in np.unique(item[item >= 0]):
        at = item == i
        ref_element[at] = ref_element_of[i](ref_element[at])
    rows: dict[str, object] = {}
    if sub.ref_uncertainty is not None:
        assert sub.ref_row is not None
        used = np.flatnonzero(sub.ref_row >= 0)
        ref_row = np.full(len(item), -1, dtype=np.int64)
        ref_row[used] = np.arange(len(used))
        rows = {"ref_uncertainty": sub.ref_uncertainty.take(sub.ref_row[used]), "ref_row": ref_row}
    return dataclasses.replace(sub, element=element_of(sub.element), ref_element=ref_element, n_elements=n_elements,
                               **rows)


def take_scores(s: Scores, elements: np.ndarray, match_of: IndexMap | None = None) -> Scores:
    """The scores of the elements ``elements``, their winning candidates renumbered by ``match_of``; no simulator
    (it cannot travel between processes; the stage's ``finish`` rebuilds one over the whole epoch)."""
    match = None if s.match is None else s.match[elements]
    if match is not None and match_of is not None:
        won = match >= 0
        match = np.full(len(match), -1, dtype=np.int64)
        match[won] = match_of(s.match[elements][won])
    return Scores(query=s.query, score=s.score[elements], measure=s.measure,
                  p_value=None if s.p_value is None else s.p_value[elements], tolerance=s.tolerance, match=match,
                  covered=None if s.covered is None else s.covered[elements])


def take_change(c: Change, elements: np.ndarray) -> Change:
    """The change of the elements ``elements``."""
    return dataclasses.replace(c, score=c.score[elements], mask=c.mask[elements], state=c.state[elements],
                               p_value=None if c.p_value is None else c.p_value[elements])
