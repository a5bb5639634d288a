"""The pairs of one recent dataset's merged candidates, grouped by reference model as ``measures.pair_sources``
groups them, but held as counts per piece of candidates rather than as an index per pair (``docs/scale.md``).

A null simulator draws 10⁵ pairs; ``pair_sources`` holds every pair's candidate index for it (4 B a candidate, and
as much again while the groups are cut: 0.8 GB at 50 M points), and reads the whole of the narrow columns it cuts
them from. Here a pass over the columns, a piece at a time, counts each group's pairs per piece of
``PIECE`` candidates; the k-th pair of a group is then found in its piece, read again. The pairs drawn are the ones
``pair_sources`` gives for the same ranks, in the same order, so a simulator over either draws the same pairs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .types import Composite, Correspondences, Dataset, Uncertainty
from .types.arrays import index_dtype, rows_copy

if TYPE_CHECKING:
    from .measures import PairGroup

PIECE = 1 << 16  # candidates counted, and later read again, at a time


@dataclass(frozen=True)
class CountedSource:
    """One group's pairs (``group``: −1 for the per-candidate reference models, else the reference item), counted
    per piece of candidates; ``subset`` makes the ``PairGroup`` of some of them, as ``PairSource.subset`` does."""

    corr: Correspondences
    group: int
    cumulative: np.ndarray  # the group's pairs in the pieces before each piece, and in all (n_pieces + 1)
    query_position: np.ndarray
    u_q: Uncertainty
    u_r: Uncertainty
    query_per_candidate: bool
    u_q_per_candidate: bool

    @property
    def size(self) -> int:
        """Number of pairs in the group."""
        return int(self.cumulative[-1])

    def candidates(self, ranks: np.ndarray) -> np.ndarray:
        """The candidate index of each of the group's pairs ``ranks`` (in candidate order), in the order given."""
        ranks = np.asarray(ranks, dtype=np.int64)
        piece = np.searchsorted(self.cumulative, ranks, side="right") - 1
        out = np.empty(len(ranks), dtype=index_dtype(len(self.corr.ref_item)))
        for p in np.unique(piece):
            at = np.flatnonzero(piece == p)
            start = int(p) * PIECE
            members = np.flatnonzero(_group_mask(self.corr, start, start + PIECE, self.group)) + start
            out[at] = members[ranks[at] - self.cumulative[p]]
        return out

    def subset(self, sel: np.ndarray, mu_q: np.ndarray | None = None, mu_r: np.ndarray | None = None
               ) -> PairGroup:
        """The pairs ``sel`` (ranks in the group) as a ``PairGroup``, optionally with other means."""
        from .measures import PairGroup

        corr = self.corr
        cand = self.candidates(sel)
        elem = corr.element[cand]
        if mu_q is None:
            mu_q = self.query_position[cand if self.query_per_candidate else elem]
        ref_rows = corr.ref_row if self.group < 0 else corr.ref_element
        ref_items = corr.ref_item[cand] if self.group < 0 else np.full(len(cand), self.group,
                                                                       dtype=corr.ref_item.dtype)
        return PairGroup(cand, elem, mu_q, self.u_q.take(cand if self.u_q_per_candidate else elem),
                         corr.position[cand] if mu_r is None else mu_r, self.u_r.take(ref_rows[cand]),
                         ref_items, corr.ref_element[cand])


def _mixtures(corr: Correspondences) -> bool:
    """Whether some candidates carry a reference model of their own (rows of ``ref_uncertainty``)."""
    return corr.ref_uncertainty is not None and corr.ref_row is not None


def _group_mask(corr: Correspondences, start: int, stop: int, group: int) -> np.ndarray:
    """Which candidates of [start, stop) are pairs of ``group`` (a correspondence, of that model)."""
    item, own = _piece(corr, start, stop)
    return own & (item >= 0) if group < 0 else ~own & (item == group)


def _piece(corr: Correspondences, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """Candidates [start, stop): their reference items, and whether each carries a model of its own."""
    item = rows_copy(corr.ref_item, start, stop)
    own = rows_copy(corr.ref_row, start, stop) >= 0 if _mixtures(corr) else np.zeros(len(item), dtype=bool)
    return item, own


def counted_sources(ds: Dataset, corr: Correspondences, reference: Composite) -> list[CountedSource]:
    """The candidate pairs of one recent dataset as ``CountedSource``s, in ``pair_sources``' order: the
    per-candidate models first, then each reference item in turn."""
    if ds.uncertainty is None:
        raise ValueError(f"recent dataset {ds.name!r} has no uncertainty: add an uncertainty stage before this one")
    n_items = len(reference.items)
    m = len(corr.ref_item)
    pieces = max(1, -(-m // PIECE))
    counts = np.zeros((pieces, n_items + 1), dtype=np.int64)  # column 0: the per-candidate models
    for p in range(pieces):
        item, own = _piece(corr, p * PIECE, min(m, (p + 1) * PIECE))
        found = item >= 0
        counts[p, 0] = np.count_nonzero(own & found)
        counts[p, 1:] = np.bincount(item[found & ~own], minlength=n_items)[:n_items]
    per_candidate = corr.query_position is not None
    qpos = corr.query_position if corr.query_position is not None else ds.element_positions()
    u_q, u_q_rows = (ds.uncertainty, False) if corr.query_uncertainty is None else (corr.query_uncertainty, True)
    out = []
    for column in range(n_items + 1):
        total = counts[:, column]
        if not total.any():
            continue
        group = column - 1
        if group < 0:
            u_r = corr.ref_uncertainty
        else:
            u_r = reference.items[group].dataset.uncertainty
            if u_r is None:
                raise ValueError(f"reference dataset {reference.items[group].dataset.name!r} has no uncertainty")
        assert u_r is not None
        out.append(CountedSource(corr, group, np.r_[0, np.cumsum(total)], qpos, u_q, u_r, per_candidate, u_q_rows))
    return out
