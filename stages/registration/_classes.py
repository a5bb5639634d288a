"""Registering on some LAS classes only (``classes: [2]``: the ground): which elements of the twin and of the recent
data the fit uses. The transform found on them is applied to every point of the recent data."""

from __future__ import annotations

import numpy as np

from gdt_pipeline import Composite, Dataset, StageError

MIN_CLASS_POINTS = 100  # fewer points than this on either side cannot constrain six parameters robustly
CLASS_FIELD = "classification"


def _class_mask(ds: Dataset, classes: list[int], side: str, method: str) -> np.ndarray:
    """Which elements of ``ds`` carry one of ``classes``; an error naming the dataset when it has no classes."""
    values = ds.fields.get(CLASS_FIELD)
    if values is None:
        how = ("a mesh has none" if ds.faces is not None else
               "read it with the LAS reader keeping `classification` in the input's `attributes`")
        raise StageError(f"{method}: `classes: {classes}` but {side} dataset {ds.name!r} has no per-point "
                         f"classification ({how}); drop `classes` or give LAS/LAZ input")
    return np.isin(np.asarray(values), classes)


def _check_count(counts: dict[str, int], classes: list[int], side: str, method: str) -> None:
    total = sum(counts.values())
    if total < MIN_CLASS_POINTS:
        per = ", ".join(f"{name!r} {n:,}" for name, n in counts.items())
        raise StageError(f"{method}: `classes: {classes}` selects {total:,} points of the {side} ({per}; at least "
                         f"{MIN_CLASS_POINTS} wanted): check the class numbers (ASPRS: 2 ground, 6 building)")


def recent_elements(recent: list[Dataset], classes: list[int] | None, method: str) -> list[np.ndarray | None]:
    """Per recent dataset the elements to fit (None: all of them)."""
    if classes is None:
        return [None] * len(recent)
    picks = [np.flatnonzero(_class_mask(d, classes, "the recent", method)) for d in recent]
    _check_count({d.name: len(p) for d, p in zip(recent, picks, strict=True)}, classes, "recent data", method)
    return list(picks)


def reference_elements(reference: Composite, classes: list[int] | None, method: str) -> list[np.ndarray]:
    """Per twin item the visible elements to fit (of ``classes`` when given)."""
    picks = []
    for it in reference.items:
        keep = it.visible if classes is None else it.visible & _class_mask(it.dataset, classes, "the twin's", method)
        picks.append(np.flatnonzero(keep))
    if classes is not None:
        _check_count({it.key: len(p) for it, p in zip(reference.items, picks, strict=True)}, classes, "twin",
                     method)
    return picks


# ASPRS classes that stay put between epochs: ground, building, rail, road surface, bridge deck. The others
# (unclassified, vegetation, water, noise, wires) move, grow or come and go.
STABLE_CLASSES = (2, 6, 10, 11, 17)
MAX_UNSTABLE_SHARE = 0.25


def class_hint(recent: list[Dataset], classes: list[int] | None) -> str | None:
    """A warning when the fit uses every class of classified data and much of it is in classes that change."""
    values = [d.fields[CLASS_FIELD] for d in recent if CLASS_FIELD in d.fields]
    if classes is not None or not values:
        return None
    cls = np.concatenate(values)
    unstable = float(np.mean(~np.isin(cls, STABLE_CLASSES)))
    if unstable <= MAX_UNSTABLE_SHARE:
        return None
    found = ", ".join(str(c) for c in np.unique(cls[~np.isin(cls, STABLE_CLASSES)]))
    return (f"the fit uses every LAS class, and {unstable:.0%} of the recent points (classes {found}) are in classes "
            f"that change between epochs (more than {MAX_UNSTABLE_SHARE:.0%}); register on the stable ones, e.g. "
            f"`classes: [2]` (ground)")
