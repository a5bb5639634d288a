"""The candidate pairs a distance stage scores and its null simulator draws from: grouped by reference model, each
group's pairs exactly the correspondences' found candidates of that item, with no column copied per candidate; and
the same pairs counted per piece of candidates (``pair_counts``), which draw the same null scores."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gdt_pipeline import (
    Composite,
    CompositeItem,
    Correspondences,
    Dataset,
    GaussianUncertainty,
    MixtureUncertainty,
    pair_counts,
)
from gdt_pipeline.measures import NullSimulation, pair_groups, pair_sources
from gdt_pipeline.pair_counts import counted_sources
from gdt_pipeline.types import MappedRows
from gdt_pipeline.types.arrays import index_dtype


def _item(key: str, ds: Dataset) -> CompositeItem:
    n = ds.n_elements
    return CompositeItem(key, ds, "E0", np.zeros(n), np.full(n, np.nan), np.zeros(n), np.ones(n, bool))


def _scene(rng: np.random.Generator) -> tuple[Dataset, Correspondences, Composite]:
    a = Dataset("a", "as-designed", rng.uniform(0, 1, (300, 3)), uncertainty=GaussianUncertainty.isotropic(0.002))
    b = Dataset("b", "as-designed", rng.uniform(0, 1, (200, 3)), uncertainty=GaussianUncertainty.isotropic(0.005))
    ref = Composite((_item("E0_a", a), _item("E0_b", b)))
    rec = Dataset("rec", "as-is", rng.uniform(0, 1, (400, 3)), uncertainty=GaussianUncertainty.isotropic(0.001))
    m = 900  # two or three candidates an element, some without a correspondence (item −1)
    element = np.sort(rng.integers(0, 400, m))
    item = rng.choice([-1, 0, 1], m, p=[0.2, 0.5, 0.3])
    ref_element = np.where(item == 0, rng.integers(0, 300, m), np.where(item == 1, rng.integers(0, 200, m), -1))
    position = np.where((item == 0)[:, None], a.points[np.maximum(ref_element, 0) % 300],
                        b.points[np.maximum(ref_element, 0) % 200])
    corr = Correspondences(0, item, ref_element, position, np.zeros(m), element=element, n_elements=400)
    return rec, corr, ref


def test_each_group_holds_its_items_found_candidates() -> None:
    rec, corr, ref = _scene(np.random.default_rng(11))
    sources = pair_sources(rec, corr, ref)
    assert [int(s.ref_item[s.idx][0]) for s in sources] == [0, 1]
    for item, src in zip((0, 1), sources, strict=True):
        expected = np.flatnonzero(corr.ref_item == item)
        assert np.array_equal(src.idx, expected) and src.idx.dtype == index_dtype(len(corr.ref_item))
        g = src.whole()
        assert np.array_equal(g.ref_items, corr.ref_item[expected])
        assert np.array_equal(g.ref_elements, corr.ref_element[expected])
        assert np.array_equal(g.elements, corr.element[expected])
        assert np.array_equal(g.mu_q, rec.points[corr.element[expected]])
        assert np.array_equal(g.mu_r, corr.position[expected])
        assert np.allclose(g.u_r.cov, ref.items[item].dataset.uncertainty.cov[0])
        # the item column is one value seen at every candidate, not a copy of 4 B a candidate
        assert src.ref_item.strides == (0,) and len(src.ref_item) == len(corr.ref_item)
        assert src.element is corr.element and src.ref_element is corr.ref_element
    assert sum(len(g.idx) for g in pair_groups(rec, corr, ref)) == int(np.count_nonzero(corr.ref_item >= 0))


def test_the_null_simulation_draws_from_every_group() -> None:
    rec, corr, ref = _scene(np.random.default_rng(12))
    sources = pair_sources(rec, corr, ref)
    drawn = []

    def measure(g, rng):  # the score of a simulated pair is the reference item it was drawn for
        drawn.append(g.ref_items.copy())
        return g.ref_items.astype(float), None, np.zeros(0)

    scores = NullSimulation(sources, measure)(np.random.default_rng(0), 4000)
    sizes = np.array([len(s.idx) for s in sources])
    assert len(scores) == 4000 and set(np.unique(scores)) == {0.0, 1.0}
    # pairs drawn uniformly from all pairs: each group's share follows its size (binomial, 5 σ)
    share = np.mean(scores == 1.0)
    p = sizes[1] / sizes.sum()
    assert abs(share - p) < 5 * np.sqrt(p * (1 - p) / 4000)


def _mapped(values: np.ndarray, folder: Path) -> MappedRows:
    """``values`` as a read-only map of a file of their own (as the candidate sink hands merged columns on)."""
    path = folder / f"column-{len(list(folder.iterdir()))}.bin"
    values = np.ascontiguousarray(values)
    path.write_bytes(values.tobytes())
    return MappedRows(path, dtype=values.dtype, mode="r", shape=values.shape)


def _with_mixtures(corr: Correspondences, rng: np.random.Generator, folder: Path) -> Correspondences:
    """The scene's candidates with a model of their own on about a third of them, every column a scratch map."""
    m = len(corr.ref_item)
    mix = MixtureUncertainty(np.ones((m, 1)), np.zeros((m, 1, 3)),
                             np.broadcast_to(np.eye(3), (m, 1, 3, 3)) * rng.uniform(1e-6, 4e-6, (m, 1, 1, 1)))
    rows = np.where((rng.uniform(size=m) < 0.35) & (corr.ref_item >= 0), np.arange(m), -1).astype(np.int32)
    return Correspondences(0, _mapped(corr.ref_item.astype(np.int32), folder),
                           _mapped(corr.ref_element.astype(np.int32), folder), _mapped(corr.position, folder),
                           corr.distance, element=_mapped(corr.element.astype(np.int32), folder), n_elements=400,
                           ref_uncertainty=mix, ref_row=_mapped(rows, folder))


@pytest.mark.parametrize("mixtures", [False, True])
def test_counted_pairs_are_the_pairs_pair_sources_give(mixtures: bool, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pair_counts, "PIECE", 37)  # 900 candidates in 25 pieces, the last one short
    rng = np.random.default_rng(13)
    rec, corr, ref = _scene(rng)
    if mixtures:
        corr = _with_mixtures(corr, rng, tmp_path)
    indexed, counted = pair_sources(rec, corr, ref), counted_sources(rec, corr, ref)
    assert [s.size for s in counted] == [len(s.idx) for s in indexed] and len(indexed) == 2 + mixtures
    for a, b in zip(indexed, counted, strict=True):
        assert np.array_equal(b.candidates(np.arange(b.size)), a.idx)
        ranks = rng.integers(0, a.size, 200)  # drawn with repeats, in any order, as a simulator draws them
        ga, gb = a.subset(ranks), b.subset(ranks)
        for name in ("idx", "elements", "mu_q", "mu_r", "ref_items", "ref_elements"):
            assert np.array_equal(getattr(ga, name), getattr(gb, name)), name
            assert getattr(ga, name).dtype == getattr(gb, name).dtype, name
        assert np.array_equal(ga.u_q.covariance(200), gb.u_q.covariance(200))
        assert np.array_equal(ga.u_r.covariance(200), gb.u_r.covariance(200))

    def measure(g, rng):  # a score that depends on every field a measure reads
        n = len(g.idx)
        spread = np.trace(g.u_q.covariance(n) + g.u_r.covariance(n), axis1=1, axis2=2)
        return np.linalg.norm(g.mu_q - g.mu_r, axis=1) / np.sqrt(spread) + g.ref_items, None, np.zeros(0)

    drawn = [NullSimulation(sources, measure)(np.random.default_rng(5), 3000) for sources in (indexed, counted)]
    assert np.array_equal(drawn[0], drawn[1])
