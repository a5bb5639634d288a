"""Element sets made one at a time as the writer reads them, so that a large epoch is written holding one set's
arrays (its packed covariances, float32 scores), never every set's at once; and point sets whose per-element
arrays are made a run of rows at a time, so that a large set written in parts holds one part's."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import overload

import numpy as np

from .elements import ElementSet


@dataclass(frozen=True)
class RowsOnDemand:
    """A point set whose ``ElementSet`` is made for rows [start, stop) on each ``rows`` call; what the writer reads
    of the whole set (its points for the frame and the preview, states and visibility for the preview, its identity
    and item) it holds as they are."""

    key: str
    points: np.ndarray
    state: np.ndarray
    visible: np.ndarray
    identity: dict[str, str] | None
    item: dict[str, str] | None
    make: Callable[[int, int], ElementSet]
    kind: str = "points"

    @property
    def n_elements(self) -> int:
        """Number of points."""
        return len(self.points)

    def rows(self, start: int, stop: int) -> ElementSet:
        """The set of rows [start, stop), checked to be that many points of this set."""
        es = self.make(start, stop)
        if es.key != self.key or es.n_elements != stop - start:
            raise ValueError(f"element set {self.key}: rows {start}:{stop} made as {es.key!r} with "
                             f"{es.n_elements} elements")
        return es


# what the writer takes for one set: the set, or a point set made a run of rows at a time
SetLike = ElementSet | RowsOnDemand


def whole(es: SetLike) -> ElementSet:
    """The whole element set (a ``RowsOnDemand``'s every row made at once: for sets written as one prim)."""
    return es.rows(0, es.n_elements) if isinstance(es, RowsOnDemand) else es


class SetsOnDemand(Sequence[ElementSet]):
    """A sequence of element sets whose keys are known beforehand and whose arrays are made on each read
    (``make(i)``); ``keys`` lets the writer check the keys without making any set."""

    def __init__(self, keys: Sequence[str], make: Callable[[int], ElementSet]) -> None:
        self.keys = list(keys)
        self._make = make

    def __len__(self) -> int:
        return len(self.keys)

    @overload
    def __getitem__(self, i: int) -> ElementSet: ...

    @overload
    def __getitem__(self, i: slice) -> list[ElementSet]: ...

    def __getitem__(self, i: int | slice) -> ElementSet | list[ElementSet]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        if not -len(self) <= i < len(self):
            raise IndexError(f"element set {i} of {len(self)}")
        i %= len(self)
        es = self._make(i)
        if es.key != self.keys[i]:
            raise ValueError(f"element set {i}: made with key {es.key!r}, announced as {self.keys[i]!r}")
        return es

    def __iter__(self) -> Iterator[ElementSet]:
        return (self[i] for i in range(len(self)))


def set_keys(elements: Sequence[ElementSet]) -> list[str]:
    """The sets' keys, without making the sets of a ``SetsOnDemand``."""
    return list(elements.keys) if isinstance(elements, SetsOnDemand) else [e.key for e in elements]
