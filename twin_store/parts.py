"""Large point sets in parts: consecutive rows of at most ``PART_ELEMENTS`` points, each a prim of its own.

A USD array is one value, so a set written as one prim is built whole in memory as USD arrays (about 140 B a point
beside the set's own columns) and a later epoch that changes one state restates every array of the set. A large set
(see ``payloads``) is therefore written in parts: ``/Twin/<key>`` is an Xform holding the set's translate (its
points' origin), its identity and item, and ``gdt:parts`` (customData: its number of elements and the rows a part
holds); its children ``part_0000``, ``part_0001``, ... are Points prims holding consecutive rows, relative
to that origin, each in a payload layer of its own. Writing holds one part's arrays at a time, and a later epoch
restates only the parts whose values changed, on the part prims. Read back (``read_set``, ``set_values``), the parts
are one set in row order, so segments' member rows and every reader see the set as before. A set written before
parts (one prim) reads and takes later epochs as it always did.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator

import numpy as np
from pxr import Usd, UsdGeom

from .elements import (
    PER_ELEMENT,
    READ_PRIMVARS,
    ElementSet,
    diagonal,
    identity_of,
    item_of,
    override_element_set,
    primvar_array,
    read_element_set,
    restate_prim_visibility,
    set_origin,
    uncertainty_model_of,
)
from .errors import TwinStoreError
from .set_source import RowsOnDemand, SetLike

PART_ELEMENTS = 1_000_000
PARTS_KEY = "gdt:parts"


def part_name(index: int) -> str:
    """The prim name of a set's ``index``-th part."""
    return f"part_{index:04d}"


def part_ranges(n: int, size: int) -> list[tuple[int, int]]:
    """The row ranges [start, stop) of the parts of a set of ``n`` elements, ``size`` rows a part."""
    return [(start, min(start + size, n)) for start in range(0, max(n, 1), size)]


def is_parted(prim: Usd.Prim) -> bool:
    """Whether a ``/Twin/<key>`` prim is a set written in parts."""
    return bool(prim.GetCustomDataByKey(PARTS_KEY))


def parts_info(prim: Usd.Prim) -> tuple[int, int]:
    """A parted set's element count and rows a part, as its ``gdt:parts`` records them."""
    info = prim.GetCustomDataByKey(PARTS_KEY)
    try:
        return int(info["elements"]), int(info["part_elements"])
    except (KeyError, TypeError, ValueError):
        raise TwinStoreError(f"element set {prim.GetPath()}: its {PARTS_KEY} record {dict(info)!r} does not say "
                             f"how many elements and rows a part it has; the twin is damaged") from None


def part_prims(prim: Usd.Prim) -> list[Usd.Prim]:
    """A parted set's part prims in row order (an error naming the missing ones)."""
    n, size = parts_info(prim)
    found = [prim.GetChild(part_name(i)) for i in range(len(part_ranges(n, size)))]
    missing = [part_name(i) for i, part in enumerate(found) if not part or not part.IsA(UsdGeom.Points)]
    if missing:
        raise TwinStoreError(f"element set {prim.GetPath()}: its parts {', '.join(missing)} are missing or not point "
                             f"prims (are their payloads loaded?); the twin is damaged")
    return found


def rows_of(es: SetLike, start: int, stop: int) -> ElementSet:
    """Rows [start, stop) of a point set as a set of their own: the same key, ids numbered as in the whole set,
    no identity or item (those are the whole set's); a ``RowsOnDemand`` makes only those rows."""
    if isinstance(es, RowsOnDemand):
        part = es.rows(start, stop)
        rows = {} if part.ids is not None else {"ids": np.arange(start, stop, dtype=np.int64)}
    else:
        part = es
        rows = {name: np.asarray(getattr(es, name))[start:stop] for name in PER_ELEMENT
                if getattr(es, name) is not None}
        if es.ids is None:
            rows["ids"] = np.arange(start, stop, dtype=np.int64)
    return dataclasses.replace(part, identity=None, item=None, **rows)


def override_parted_set(prim: Usd.Prim, es: SetLike, epoch_id: str) -> None:
    """Author on the stage's edit target the values of a known parted set that differ from what is stored, part
    by part (an unchanged part gets no opinion), and the set's visibility."""
    n, size = parts_info(prim)
    if es.kind != "points" or es.n_elements != n:
        raise TwinStoreError(f"epoch {epoch_id}: geometry of an existing element set cannot change: {es.key} has "
                             f"{n} points, the epoch gives {es.n_elements} {es.kind} elements (changed geometry "
                             f"comes in as a new set)")
    frame = (set_origin(prim), diagonal(np.asarray(es.points, dtype=np.float64)))
    for part, (start, stop) in zip(part_prims(prim), part_ranges(n, size), strict=True):
        override_element_set(part, rows_of(es, start, stop), epoch_id, frame)
    restate_prim_visibility(prim, bool(np.any(es.visible)))


def read_set(prim: Usd.Prim) -> ElementSet:
    """The element set a composed ``/Twin/<key>`` prim holds, in world coordinates, whether in parts or one prim."""
    if not is_parted(prim):
        return read_element_set(prim)
    n, size = parts_info(prim)
    prims, ranges = part_prims(prim), part_ranges(n, size)
    origin = set_origin(prim)
    points = _column(prim, prims, ranges, lambda one: np.asarray(UsdGeom.Points(one).GetPointsAttr().Get(),
                                                                 dtype=np.float64).reshape(-1, 3) + origin)
    ids = _column(prim, prims, ranges, lambda one: np.asarray(UsdGeom.Points(one).GetIdsAttr().Get(), np.int64))
    values = {field: _column(prim, prims, ranges, lambda one, field=field: primvar_array(one, field))
              for field in READ_PRIMVARS}
    return ElementSet(key=prim.GetName(), kind="points", points=points, faces=None,
                      uncertainty_model=uncertainty_model_of(prims[0]), ids=ids, identity=identity_of(prim),
                      item=item_of(prim), **values)


def _column(prim: Usd.Prim, prims: list[Usd.Prim], ranges: list[tuple[int, int]],
            read: Callable[[Usd.Prim], np.ndarray | None]) -> np.ndarray | None:
    """One value over a parted set's rows, read part by part into one array (None where no part has it), so that
    reading holds the set's columns and one part's value, never the parts' arrays all at once."""
    column = None
    for one, (start, stop) in zip(prims, ranges, strict=True):
        value = read(one)
        if value is None and column is None and all(read(p) is None for p in prims[1:]):
            return None  # a value the set does not have (no part has it)
        if value is None or len(value) != stop - start:
            raise TwinStoreError(f"element set {prim.GetPath()}: its part {one.GetName()} holds "
                                 f"{'no' if value is None else len(value)} values for rows {start}:{stop}; the "
                                 f"twin is damaged")
        if column is None:
            column = np.empty((ranges[-1][1], *value.shape[1:]), value.dtype)
        column[start:stop] = value
    return column


def set_values(prim: Usd.Prim, field: str) -> np.ndarray | None:
    """One per-element value of a set (a field of ``READ_PRIMVARS``) over all its elements, its parts' in row
    order; None where it has none."""
    return _over_parts(prim, lambda one: primvar_array(one, field))


def set_points(prim: Usd.Prim) -> np.ndarray:
    """A set's points (mesh vertices) as float32 relative to its origin (``set_origin``), its parts' in row order."""
    return _over_parts(prim, lambda one: np.asarray(UsdGeom.PointBased(one).GetPointsAttr().Get(),
                                                    dtype=np.float32).reshape(-1, 3))


def iter_point_parts(prim: Usd.Prim) -> Iterator[tuple[int, np.ndarray]]:
    """A point set's points part by part: each part's first row and its points (float32, relative to the set's
    origin); one piece for a set in one prim. A reader that reduces them as they come holds one part."""
    if not is_parted(prim):
        yield 0, set_points(prim)
        return
    n, size = parts_info(prim)
    for one, (start, stop) in zip(part_prims(prim), part_ranges(n, size), strict=True):
        local = set_points(one)
        if len(local) != stop - start:
            raise TwinStoreError(f"element set {prim.GetPath()}: its part {one.GetName()} holds {len(local)} points "
                                 f"for rows {start}:{stop}; the twin is damaged")
        yield start, local


def _over_parts(prim: Usd.Prim, read: Callable[[Usd.Prim], np.ndarray | None]) -> np.ndarray | None:
    """``read`` of a one-prim set, or of a parted set's parts into one array."""
    if not is_parted(prim):
        return read(prim)
    n, size = parts_info(prim)
    return _column(prim, part_prims(prim), part_ranges(n, size), read)


def set_extent(prim: Usd.Prim) -> np.ndarray | None:
    """A set's local lower and upper corners from its (parts') extents; None where one has none."""
    prims = part_prims(prim) if is_parted(prim) else [prim]
    extents = [UsdGeom.PointBased(one).GetExtentAttr().Get() for one in prims]
    if any(e is None for e in extents):
        return None
    corners = np.concatenate([np.asarray(e, dtype=np.float64) for e in extents])
    return np.stack([corners.min(axis=0), corners.max(axis=0)])
