"""The pairs of one recent dataset's merged candidates, grouped by reference model as ``measures.pair_sources``
groups them, but held as counts per piece of candidates rather than as an index per pair (``docs/scale.md``).

A null simulator draws 10⁵ pairs; ``pair_sources`` holds every pair's candidate index for it (4 B a candidate, and
as much again while the groups are cut: 0.8 GB at 50 M points), and reads the whole of the narrow columns it cuts
them from. Here a pass over the columns, a piece at a time, counts each group's pairs per piece of
``PIECE`` candidates; the k-th pair of a group is then found in its piece, read again. The pairs drawn are the ones
``pair_sources`` gives for the same ranks, in the same order, so a simulator over either draws the same pairs.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .pairs import MIXTURES, PairGroup, PairSource, group_source
from .types import Composite, Correspondences, Dataset, Uncertainty
from .types.arrays import index_dtype, rows_copy

PIECE = 1 << 16  # candidates counted, and later read again, at a time


@dataclass(frozen=True)
class CountedSource:
    """One group's pairs, counted per piece of candidates; ``subset`` makes the ``PairGroup`` of some of them
    through the group's ``PairSource`` (``source``, its ``idx`` left empty)."""

    source: PairSource
    group: int  # MIXTURES, or the reference item
    cumulative: np.ndarray  # the group's pairs in the pieces before each piece, and in all (n_pieces + 1)
    ref_item: np.ndarray  # the correspondences' columns the groups are told apart by
    ref_row: np.ndarray | None

    @property
    def size(self) -> int:
        """Number of pairs in the group."""
        return int(self.cumulative[-1])

    @property
    def u_q(self) -> Uncertainty:
        """The query side's model (what the threshold's report names)."""
        return self.source.u_q

    @property
    def u_r(self) -> Uncertainty:
        """The reference side's model."""
        return self.source.u_r

    def candidates(self, ranks: np.ndarray) -> np.ndarray:
        """The candidate index of each of the group's pairs ``ranks`` (in candidate order), in the order given."""
        ranks = np.asarray(ranks, dtype=np.int64)
        piece = np.searchsorted(self.cumulative, ranks, side="right") - 1
        out = np.empty(len(ranks), dtype=index_dtype(len(self.ref_item)))
        for p in np.unique(piece):
            at = np.flatnonzero(piece == p)
            start = int(p) * PIECE
            item, own = _piece(self.ref_item, self.ref_row, start, start + PIECE)
            mask = own & (item >= 0) if self.group == MIXTURES else ~own & (item == self.group)
            members = np.flatnonzero(mask) + start
            out[at] = members[ranks[at] - self.cumulative[p]]
        return out

    def subset(self, sel: np.ndarray, mu_q: np.ndarray | None = None, mu_r: np.ndarray | None = None
               ) -> PairGroup:
        """The pairs ``sel`` (ranks in the group) as a ``PairGroup``, optionally with other means."""
        cand = self.candidates(sel)
        return dataclasses.replace(self.source, idx=cand).subset(np.arange(len(cand)), mu_q, mu_r)


def _piece(ref_item: np.ndarray, ref_row: np.ndarray | None, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """Candidates [start, stop): their reference items, and whether each carries a model of its own."""
    item = rows_copy(ref_item, start, stop)
    own = rows_copy(ref_row, start, stop) >= 0 if ref_row is not None else np.zeros(len(item), dtype=bool)
    return item, own


def counted_sources(ds: Dataset, corr: Correspondences, reference: Composite) -> list[CountedSource]:
    """The candidate pairs of one recent dataset as ``CountedSource``s, in ``pair_sources``' order: the
    per-candidate models first, then each reference item in turn."""
    if ds.uncertainty is None:
        raise ValueError(f"recent dataset {ds.name!r} has no uncertainty: add an uncertainty stage before this one")
    n_items = len(reference.items)
    m = len(corr.ref_item)
    rows = corr.ref_row if corr.ref_uncertainty is not None else None
    counts = np.zeros((max(1, -(-m // PIECE)), n_items + 1), dtype=np.int64)  # column 0: the per-candidate models
    for p in range(len(counts)):
        item, own = _piece(corr.ref_item, rows, p * PIECE, min(m, (p + 1) * PIECE))
        found = item >= 0
        counts[p, 0] = np.count_nonzero(own & found)
        counts[p, 1:] = np.bincount(item[found & ~own], minlength=n_items)[:n_items]
    empty = np.zeros(0, dtype=index_dtype(m))
    return [CountedSource(group_source(ds, corr, reference, column - 1, empty), column - 1,
                          np.r_[0, np.cumsum(counts[:, column])], corr.ref_item, rows)
            for column in range(n_items + 1) if counts[:, column].any()]
