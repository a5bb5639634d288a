"""Element sets made one at a time as the writer reads them, so that a large epoch is written holding one set's
arrays (its packed covariances, float32 scores), never every set's at once."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import overload

from .elements import ElementSet


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
