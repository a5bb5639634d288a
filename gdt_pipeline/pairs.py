"""The candidate pairs of one recent dataset, grouped so that each group has one reference uncertainty model: as
index-only sources (``PairSource``) or materialised (``PairGroup``: means and uncertainties of both sides). Re-exported
by ``measures``, where distance stages and plugins find them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .types import Composite, Correspondences, Dataset, Uncertainty
from .types.arrays import index_dtype


@dataclass(frozen=True)
class PairGroup:
    """Candidate pairs of one recent dataset sharing one reference model: candidate indices, the query elements they
    belong to, means and uncertainties of both sides."""

    idx: np.ndarray
    elements: np.ndarray
    mu_q: np.ndarray
    u_q: Uncertainty
    mu_r: np.ndarray
    u_r: Uncertainty
    ref_items: np.ndarray
    ref_elements: np.ndarray
    normal: np.ndarray | None = None  # local surface normal per pair, for tests along the normal

    @property
    def size(self) -> int:
        """Number of pairs."""
        return len(self.idx)

    def subset(self, sel: np.ndarray, mu_q: np.ndarray | None = None, mu_r: np.ndarray | None = None) -> PairGroup:
        """The pairs ``sel`` of this group, optionally with other means (simulated ones)."""
        return PairGroup(self.idx[sel], self.elements[sel], self.mu_q[sel] if mu_q is None else mu_q,
                         self.u_q.take(sel), self.mu_r[sel] if mu_r is None else mu_r, self.u_r.take(sel),
                         self.ref_items[sel], self.ref_elements[sel], None if self.normal is None else self.normal[sel])


@dataclass(frozen=True)
class PairSource:
    """Where the pairs of one group come from, without copying them: the candidate indices ``idx`` and the arrays
    they index (the correspondences', the datasets'). ``subset`` makes a ``PairGroup`` of some of them on demand, so
    that the null simulator of a distance stage keeps 8 bytes per pair alive rather than a copy of every mean and
    covariance."""

    idx: np.ndarray
    element: np.ndarray
    query_position: np.ndarray
    u_q: Uncertainty
    position: np.ndarray
    u_r: Uncertainty
    ref_rows: np.ndarray
    ref_item: np.ndarray
    ref_element: np.ndarray
    query_per_candidate: bool  # query_position holds one row per candidate (else one per query element)
    u_q_per_candidate: bool = False  # u_q holds one row per candidate (a neighbourhood expectation's)

    @property
    def size(self) -> int:
        """Number of pairs."""
        return len(self.idx)

    def subset(self, sel: np.ndarray, mu_q: np.ndarray | None = None, mu_r: np.ndarray | None = None) -> PairGroup:
        """The pairs ``sel`` (positions in ``idx``) as a ``PairGroup``, optionally with other means."""
        cand = self.idx[sel]
        elem = self.element[cand]
        if mu_q is None:
            mu_q = self.query_position[cand if self.query_per_candidate else elem]
        return PairGroup(cand, elem, mu_q, self.u_q.take(cand if self.u_q_per_candidate else elem),
                         self.position[cand] if mu_r is None else mu_r, self.u_r.take(self.ref_rows[cand]),
                         self.ref_item[cand], self.ref_element[cand])

    def whole(self) -> PairGroup:
        """Every pair of the group."""
        return self.subset(np.arange(len(self.idx)))


def pair_sources(ds: Dataset, corr: Correspondences, reference: Composite) -> list[PairSource]:
    """The candidate pairs of one recent dataset as ``PairSource``s, one per reference uncertainty model."""
    if ds.uncertainty is None:
        raise ValueError(f"recent dataset {ds.name!r} has no uncertainty: add an uncertainty stage before this one")
    # the null simulator keeps these indices for the threshold: int32 where they fit (4 B a candidate less)
    found = np.flatnonzero(corr.found).astype(index_dtype(len(corr.found)), copy=False)
    sources = []
    rows = corr.ref_row
    if corr.ref_uncertainty is not None and rows is not None:  # per-candidate reference models (mixtures)
        over = found[rows[found] >= 0]
        if over.size:
            sources.append(group_source(ds, corr, reference, MIXTURES, over))
        found = found[rows[found] < 0]
    for item in np.unique(corr.ref_item[found]):
        sources.append(group_source(ds, corr, reference, int(item), found[corr.ref_item[found] == item]))
    return sources


MIXTURES = -1  # the group of the candidates carrying a reference model of their own


def group_source(ds: Dataset, corr: Correspondences, reference: Composite, group: int, idx: np.ndarray
                 ) -> PairSource:
    """The pairs ``idx`` of one group (``MIXTURES``, or a reference item) of a recent dataset as a ``PairSource``."""
    if ds.uncertainty is None:
        raise ValueError(f"recent dataset {ds.name!r} has no uncertainty: add an uncertainty stage before this one")
    # per candidate when the correspondences carry query positions, else per element
    per_candidate = corr.query_position is not None
    qpos = corr.query_position if corr.query_position is not None else ds.element_positions()
    u_q, u_q_rows = (ds.uncertainty, False) if corr.query_uncertainty is None else (corr.query_uncertainty, True)
    if group == MIXTURES:
        assert corr.ref_uncertainty is not None and corr.ref_row is not None
        return PairSource(idx, corr.element, qpos, u_q, corr.position, corr.ref_uncertainty, corr.ref_row,
                          corr.ref_item, corr.ref_element, per_candidate, u_q_rows)
    ref = reference.items[group].dataset
    if ref.uncertainty is None:
        raise ValueError(f"reference dataset {ref.name!r} has no uncertainty")
    # every pair of this source names this item: a stride-0 column rather than the correspondences' (the
    # simulator holds its columns from the distance stage to the threshold: 4 B a candidate, 0.2 GB at 50 M)
    item_column = np.broadcast_to(corr.ref_item.dtype.type(group), corr.ref_item.shape)
    return PairSource(idx, corr.element, qpos, u_q, corr.position, ref.uncertainty, corr.ref_element, item_column,
                      corr.ref_element, per_candidate, u_q_rows)


def pair_groups(ds: Dataset, corr: Correspondences, reference: Composite) -> list[PairGroup]:
    """The candidate pairs of one recent dataset, grouped so that each group has one reference uncertainty model."""
    return [src.whole() for src in pair_sources(ds, corr, reference)]
