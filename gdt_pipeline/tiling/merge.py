"""Putting tiles' core results back together, element by element, and proving that none was lost or doubled.

Each tile returns, per recent dataset, the results of its core elements only, already in global numbering; the
merge puts them in element order. Correspondences are put in element order too (stable, tile by tile), which is the
order an untiled run leaves them in (``runner.stage_call.element_ordered``), so candidate numbers, and each
element's winning candidate, mean the same in both.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np

from ..errors import GdtError
from ..memory import release_pages
from ..scratch import reserved_map
from ..types import (
    Change,
    Correspondences,
    Dataset,
    GaussianUncertainty,
    MappedRows,
    Scores,
    Uncertainty,
    concat_uncertainty,
)
from ..types.arrays import index_dtype
from .candidate_sink import candidate_places


@dataclass(frozen=True)
class ElementOrder:
    """Where each element of one dataset sits in the tiles' concatenated core results."""

    position: np.ndarray  # position[e]: index of element e in the concatenation

    @classmethod
    def check(cls, name: str, core_ids: Sequence[np.ndarray], n: int) -> ElementOrder:
        """The order of the concatenated core ids; an error unless every element is in exactly one tile's core."""
        ids = np.concatenate(core_ids) if core_ids else np.zeros(0, np.int64)
        counts = np.bincount(ids, minlength=n) if len(ids) else np.zeros(n, np.int64)
        if len(counts) != n or np.any(counts != 1):
            lost, doubled = int(np.sum(counts[:n] == 0)), int(np.sum(counts[:n] > 1))
            raise GdtError(f"tiling of dataset {name!r}: {lost} elements in no tile's core and {doubled} in more than "
                           f"one (of {n}); the merged result would not be the epoch's")
        position = np.empty(n, dtype=index_dtype(n))
        position[ids] = np.arange(n, dtype=position.dtype)
        return cls(position)


@dataclass(frozen=True)
class UncertaintyPiece:
    """What a tile hands back of a recent dataset: the uncertainty its stages attached to its core elements (their
    geometry is the epoch's, untouched, so it does not travel back)."""

    uncertainty: Uncertainty | None
    n_elements: int


@dataclass
class RecentSink:
    """Per recent dataset, the tiles' per-element Gaussian covariances written into place as each tile finishes, so
    that the run holds the merged rows and one tile's, not every tile's plus their concatenation (144 B a point).

    With a ``folder`` the merged rows live in a scratch file there, mapped (72 B a point on disk, none in memory): the
    writer lets go of the pages each tile wrote, and the merged dataset holds a read-only ``MappedRows`` of it, whose
    reads take pieces (``types.arrays``)."""

    sizes: Sequence[int]
    folder: Path | None = None
    cov: dict[int, np.ndarray] = field(default_factory=dict)
    dof: dict[int, float | None] = field(default_factory=dict)
    files: dict[int, IO[bytes]] = field(default_factory=dict)

    def _rows(self, d: int) -> np.ndarray:
        """Room for dataset ``d``'s covariances: in memory, or a scratch file reserved in full (so that a full disk
        is an error now, naming the folder, not a SIGBUS in the middle of a tile) and mapped for writing."""
        n = self.sizes[d]
        if self.folder is None or n == 0:
            return np.empty((n, 3, 3))
        self.files[d], rows = reserved_map(self.folder, "gdt-cov-", np.float64, (n, 3, 3), "the scans' covariances")
        return rows

    def absorb(self, pieces: list[UncertaintyPiece | None], members: Sequence[np.ndarray]) -> None:
        """Write each piece that is a per-element Gaussian with the dataset's dof into place (``members[d]``: its
        elements), and drop it from ``pieces``."""
        for d, piece in enumerate(pieces):
            u = None if piece is None else piece.uncertainty
            if not isinstance(u, GaussianUncertainty) or u.rows != piece.n_elements or u.rows == 1:
                continue
            if d in self.dof and self.dof[d] != u.dof:
                continue
            if d not in self.cov:
                self.cov[d], self.dof[d] = self._rows(d), u.dof
            self.cov[d][members[d]] = u.cov
            pages = getattr(self.cov[d], "_mmap", None)
            if pages is not None:  # the rows written are in the page cache; the process need not hold them
                release_pages(pages)
            pieces[d] = None

    def merged(self, ds: Dataset, d: int, pieces: Sequence[UncertaintyPiece | None], members: Sequence[np.ndarray],
               order: ElementOrder) -> Dataset:
        """The dataset with the uncertainty the tiles attached to their core elements (``members[t]``: tile t's)."""
        if d not in self.cov:
            return merge_recent(ds, pieces, order)  # type: ignore[arg-type]
        cov = self.cov.pop(d)
        if any(p is not None for p in pieces):  # some tile's model was not absorbed: join them the general way
            whole = GaussianUncertainty.trusted(cov, self.dof[d])  # rows of unabsorbed tiles are unset
            full = [UncertaintyPiece(whole.take(m), len(m)) if p is None else p
                    for p, m in zip(pieces, members, strict=True)]
            merged = merge_recent(ds, full, order)
            self._close(d)
            return merged
        rows = self._read_only(d, cov)
        return dataclasses.replace(ds, uncertainty=GaussianUncertainty.trusted(rows, self.dof[d]))

    def _read_only(self, d: int, cov: np.ndarray) -> np.ndarray:
        """The merged rows, read-only: the array itself, or a ``MappedRows`` of the scratch file (its writer map let
        go of; the map holds the file open, so its descriptor is closed here)."""
        file = self.files.get(d)
        if file is None:
            cov.setflags(write=False)
            return cov
        cov.flush()
        rows = MappedRows(file, dtype=np.float64, mode="r", shape=cov.shape)
        del cov
        self._close(d)
        return rows

    def _close(self, d: int) -> None:
        """Close dataset ``d``'s scratch file, if any (maps of it keep it until they go)."""
        file = self.files.pop(d, None)
        if file is not None:
            file.close()


def merge_recent(ds: Dataset, pieces: Sequence[Dataset | UncertaintyPiece], order: ElementOrder) -> Dataset:
    """The dataset with the uncertainty the tiles attached to their core elements."""
    if any(p.uncertainty is None for p in pieces) or not pieces:
        return ds
    unc = concat_uncertainty([p.uncertainty for p in pieces], [p.n_elements for p in pieces])
    if unc.rows != 1:
        unc = unc.take(order.position)
    return dataclasses.replace(ds, uncertainty=unc)


def merge_correspondences(pieces: list[Correspondences], n_elements: int, query: int, release: bool = False
                          ) -> tuple[Correspondences, list[np.ndarray]]:
    """The tiles' core candidates in element order, and per tile where each of its candidates went (``release``:
    empty ``pieces`` as they are merged, ``Correspondences.scattered``)."""
    maps = candidate_places([p.element for p in pieces])
    return Correspondences.scattered(pieces, maps, query, n_elements, release), maps


def _p_values(pieces: Sequence[Scores] | Sequence[Change], order: ElementOrder) -> np.ndarray | None:
    """The tiles' p-values in element order, NaN (no test) in a tile that scored no pair; None when no tile has any
    (the measure gives none)."""
    if all(p.p_value is None for p in pieces):
        return None
    parts = [np.full(len(p.score), np.nan) if p.p_value is None else p.p_value for p in pieces]
    return np.concatenate(parts)[order.position]


def merge_change(pieces: Sequence[Change], order: ElementOrder) -> Change:
    """The tiles' core change in element order (the threshold is the one every tile used)."""
    first = pieces[0]

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(p, name) for p in pieces])[order.position]

    return Change(query=first.query, score=cat("score"), mask=cat("mask"), state=cat("state"),
                  p_value=_p_values(pieces, order), threshold=first.threshold)
