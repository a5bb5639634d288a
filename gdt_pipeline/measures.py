"""Building blocks for distance stages (paper Sec. 4.2.1), public so that a plugin's measure reuses what the built-in
ones use:

- ``pair_sources`` and ``pair_groups``: the candidate pairs of one recent dataset, grouped so that each group has one
  reference uncertainty model, as index-only sources (``PairSource``) or materialised (``PairGroup``: means and
  uncertainties of both sides);
- ``lowest_per_element``: per element, the lowest candidate score ("the candidate with the lower change score wins");
- ``null_simulator``: scores of unchanged pairs drawn from the actual uncertainty models (``Scores.simulate``, what
  the ``calibrated_threshold`` stage needs);
- ``distance_stage``: the distance stage around a pair function, for every measure (built-in and plugins alike): it
  runs tile by tile, takes the stage's ε_T (``tolerance``), lets a measure add to the groups first (``prepare``,
  e.g. local normals) and report what it counted (``summary``); ``run_pair_measure`` is its run and
  ``attach_null_simulators`` its ``finish`` (the simulators and the reference's coverage of the elements without a
  score again over the whole epoch, after a tiled run);
- ``euclidean``: the plain (cloud-to-cloud) distance as a pair function;
- ``reference_cloud``: the composite so far as one point cloud, for measures that compare clouds rather than pairs.

A pair function (``PairMeasure``) takes a ``PairGroup`` and the stage's generator and returns, per pair, the score,
the p-value (or None) and an integration error bound (an empty array when the score is exact), as a ``Measured``
(which may also carry counts of what it did, summed over the stage's groups) or a plain 3-tuple.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any, NamedTuple

import numpy as np
from pydantic import BaseModel

from .compiled import njit
from .coverage import ReferenceCoverage
from .geometry import sample_surface
from .pair_counts import counted_sources
from .pairs import PairGroup, PairSource, pair_groups, pair_sources  # noqa: F401  (re-exported: a plugin's measure imports them from here)
from .plugins import FAMILY_SLOTS, StageContext, StageSpec, family_stage
from .types import Composite, Correspondences, Dataset, Scores, Uncertainty
from .types.arrays import index_dtype
from .types.uncertainty import describe_model

Counts = dict[str, dict[str, int]]


class Measured(NamedTuple):
    """What a pair function returns for a group: per pair the score, the p-value (None when the measure has none) and
    an integration error bound (empty when exact); ``counts`` of what it did (e.g. pairs per method or per
    integration path), which the stage sums over its groups and hands to its ``summary``."""

    score: np.ndarray
    p_value: np.ndarray | None
    error: np.ndarray
    counts: Mapping[str, Mapping[str, int]] = MappingProxyType({})


MeasureResult = Measured | tuple[np.ndarray, np.ndarray | None, np.ndarray]
PairMeasure = Callable[["PairGroup", np.random.Generator], MeasureResult]
ParamsMeasure = Callable[["PairGroup", np.random.Generator, Any], MeasureResult]
Prepare = Callable[[list["PairGroup"], int], list["PairGroup"]]
StagePrepare = Callable[[StageContext, list["PairGroup"], int], list["PairGroup"]]
Summary = Callable[[Counts], dict[str, Any]]
NullSimulator = Callable[[np.random.Generator, int], np.ndarray]
DISTANCE_REQUIRES = FAMILY_SLOTS["distance"][0]


def lowest_per_element(elements: np.ndarray, cand_score: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per element, the lowest candidate score (NaN when it has none) and the index of that candidate (−1); among
    equal scores the first candidate wins."""
    score = np.full(n, np.nan)
    match = np.full(n, -1, dtype=index_dtype(len(elements)))  # held to the fusion: int32 where it fits
    _lowest(np.ascontiguousarray(elements), np.ascontiguousarray(cand_score, dtype=np.float64),
            score, match)
    return score, match


@njit(cache=True)
def _lowest(elements: np.ndarray, cand_score: np.ndarray, score: np.ndarray, match: np.ndarray) -> None:
    # one pass in candidate order (a lexsort of a million candidates took 70 ms a dataset); NaN counts as +inf, and
    # an element whose lowest score is not finite has no match
    for i in range(len(elements)):
        value = cand_score[i]
        key = np.inf if np.isnan(value) else value
        e = elements[i]
        if match[e] < 0 or key < score[e]:
            score[e], match[e] = key, i
    for e in range(len(score)):
        if match[e] >= 0 and not np.isfinite(score[e]):
            score[e], match[e] = np.nan, -1


def _sample_offsets(u: Uncertainty, n: int, rng: np.random.Generator) -> np.ndarray:
    return u.sample(n, rng, 1)[:, 0, :]


class NullSimulation:
    """Scores of unchanged pairs drawn from the groups' models (a ``NullSimulator``); ``models`` names them (a
    Student t's ν included), for the threshold's report."""

    def __init__(self, groups: list[PairGroup] | list[PairSource], measure: PairMeasure) -> None:
        self.groups, self.measure = groups, measure
        self.sizes = np.array([g.size for g in groups])

    @property
    def models(self) -> list[str]:
        """Per distinct pair of models drawn from: "query model vs reference model"."""
        return sorted({f"{describe_model(g.u_q)} vs {describe_model(g.u_r)}" for g in self.groups})

    def __call__(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` scores of simulated unchanged pairs, the pairs drawn uniformly from the groups' pairs."""
        sizes = self.sizes
        if sizes.sum() == 0:
            return np.zeros(0)
        pick = rng.integers(0, sizes.sum(), n)
        owner = np.searchsorted(np.cumsum(sizes), pick, side="right")
        out = []
        for g_i in np.unique(owner):
            g = self.groups[g_i]
            local = pick[owner == g_i] - (sizes[:g_i].sum() if g_i else 0)
            sub = g.subset(local)
            truth = sub.mu_r
            # each side off by a draw from its own model: a Student t's tail is drawn with it
            sim = g.subset(local, mu_q=truth + _sample_offsets(sub.u_q, len(local), rng),
                           mu_r=truth + _sample_offsets(sub.u_r, len(local), rng))
            out.append(self.measure(sim, rng)[0])
        return np.concatenate(out)


def null_simulator(groups: list[PairGroup] | list[PairSource], measure: PairMeasure) -> NullSimulator:
    """Scores of unchanged pairs: both measurements of the same true position, each off by its own model's error."""
    return NullSimulation(groups, measure)


def _add_counts(total: Counts, counts: Mapping[str, Mapping[str, int]]) -> None:
    for kind, values in counts.items():
        into = total.setdefault(kind, {})
        for key, n in values.items():
            into[key] = into.get(key, 0) + int(n)


def _kept_sources(sources: list[PairSource], kept: np.ndarray | None) -> list[PairSource]:
    """The pairs of ``sources`` whose query element is ``kept`` (all when None): a tile's halo elements only serve as
    neighbours, and unpooled they may be the dearest pairs to integrate."""
    if kept is None:
        return sources
    cut = [dataclasses.replace(src, idx=src.idx[kept[src.element[src.idx]]]) for src in sources]
    return [src for src in cut if len(src.idx)]


def score_dataset(ctx: StageContext, corr: Correspondences, name: str, measure: PairMeasure,
                  prepare: Prepare | None = None, counts: Counts | None = None,
                  cover: ReferenceCoverage | None = None) -> tuple[Scores, float]:
    """The ``Scores`` of one recent dataset (lowest candidate per element, null simulator attached) and the largest
    integration error of its pairs; ``Scores.tolerance`` is left for the caller. What the measure counted is added to
    ``counts``."""
    ds = ctx["recent"][corr.query]
    m = len(corr.ref_item)
    cand_score = np.full(m, np.nan)
    cand_p = None
    worst = 0.0
    sources: list[Any] = _kept_sources(pair_sources(ds, corr, ctx["reference"]), ctx.kept(ds.element_positions()))
    groups: list[Any] = sources
    if prepare is not None:  # prepared groups (e.g. with local normals) are what the simulator must draw from
        groups = sources = prepare([src.whole() for src in sources], corr.query)
    for src in groups:
        g = src.whole() if isinstance(src, PairSource) else src  # one group's copies at a time
        result = measure(g, ctx.rng)
        s, p, err = result[0], result[1], result[2]
        if counts is not None and len(result) > 3:
            _add_counts(counts, result[3])
        cand_score[g.idx] = s
        if p is not None:
            if cand_p is None:
                cand_p = np.full(m, np.nan)
            cand_p[g.idx] = p
        if err.size:
            worst = max(worst, float(np.max(err)))
    score, match = lowest_per_element(corr.element, cand_score, ds.n_elements)
    p_value = None
    if cand_p is not None:
        p_value = np.where(match >= 0, cand_p[np.maximum(match, 0)], np.nan)
    return Scores(query=corr.query, score=score, measure=name, p_value=p_value, tolerance=None,
                  simulate=null_simulator(sources, measure), match=match,
                  covered=None if ctx.tile is not None else unmatched_coverage(ctx, ds, score, cover)), worst


def unmatched_coverage(ctx: StageContext, ds: Dataset, score: np.ndarray, cover: ReferenceCoverage | None = None
                       ) -> np.ndarray:
    """Per element, whether the reference covers its place; judged for the elements without a score (the others
    were compared, so the reference had data there); ``cover``: the test against this reference, built once for
    all of a stage's datasets. It runs over the whole epoch (a tiled run's ``finish``): the closest reference
    surface may lie far outside a tile's halo."""
    covered = np.ones(len(score), dtype=bool)
    unmatched = np.flatnonzero(np.isnan(score))
    if unmatched.size == 0:
        return covered
    positions = ds.element_positions()[unmatched]
    # the 99 % regions of the unmatched elements only: a scan's other million need no eigendecomposition
    scale = np.zeros(len(unmatched)) if ds.uncertainty is None else \
        ds.uncertainty.take(unmatched).region99(len(unmatched)).bounding_radius()
    found = (ReferenceCoverage(ctx["reference"]) if cover is None else cover)(positions, scale)
    covered[unmatched] = found.covered
    return covered


def run_pair_measure(ctx: StageContext, name: str, measure: PairMeasure, tolerance: float | None = None,
                     prepare: Prepare | None = None, summary: Summary | None = None) -> dict[str, Any]:
    """A distance stage's whole run: every candidate pair scored by ``measure``, the lowest per element kept.

    ``tolerance`` (ε_T) is reported with each ``Scores`` (raised to the largest integration error met so far);
    ``prepare(groups, query)`` may add to the pair groups of a recent dataset (e.g. local normals) first; what the
    measure counted is reported through ``summary(counts)`` (as it is without one).
    """
    out = []
    worst = 0.0
    counts: Counts = {}
    cover = ReferenceCoverage(ctx["reference"])
    with ctx.progress.task(f"{name} scores", total=len(ctx["correspondences"])) as advance:
        for corr in ctx["correspondences"]:
            scores, err = score_dataset(ctx, corr, name, measure, prepare, counts, cover)
            worst = max(worst, err)
            out.append(dataclasses.replace(scores, tolerance=None if tolerance is None else max(tolerance, worst)))
            advance()
    ctx.report(max_integration_error=worst, tolerance=tolerance)
    if summary is not None:
        ctx.report(**summary(counts))
    elif counts:
        ctx.report(counts=counts)
    return {"scores": out}


def attach_null_simulators(ctx: StageContext, measure: PairMeasure, prepare: Prepare | None = None
                           ) -> dict[str, Any]:
    """Every ``Scores`` of the epoch given the null simulator ``run_pair_measure`` attaches, over all of the epoch's
    pairs: a distance stage's ``finish`` after a tiled run (simulators are closures and stay in their tile)."""
    by_query = {c.query: c for c in ctx["correspondences"]}
    out = []
    cover = ReferenceCoverage(ctx["reference"])
    for s in ctx["scores"]:
        ds = ctx["recent"][s.query]
        # counted, not indexed: the merged candidates' columns may be maps of a scratch file (the same pairs drawn)
        sources: list[Any] = counted_sources(ds, by_query[s.query], ctx["reference"])
        if prepare is not None:  # prepared groups (local normals) are every pair's copies anyway
            sources = prepare([src.whole() for src in pair_sources(ds, by_query[s.query], ctx["reference"])],
                              s.query)
        out.append(dataclasses.replace(s, simulate=null_simulator(sources, measure),
                                       covered=unmatched_coverage(ctx, ds, s.score, cover)))
    return {"scores": out}


def distance_stage(*, name: str, measure: ParamsMeasure, params: type[BaseModel], version: str,
                   description: str = "", tolerance: Callable[[Any], float] | None = None,
                   prepare: StagePrepare | None = None, summary: Summary | None = None) -> StageSpec:
    """A distance stage from a pair function ``measure(group, rng, params)``; ``params`` is the validated model. It
    runs tile by tile (a pair's score depends on the pair only; a ``prepare`` that reads neighbourhoods declares
    them with ``ctx.neighbourhoods``) and rebuilds the null simulators over the whole epoch after a tiled run.

    ``tolerance(params)``: the ε_T the scores carry; ``prepare(ctx, groups, query)``: the pair groups of a recent
    dataset with more in them (e.g. local normals), for scoring and simulation alike; ``summary(counts)``: the
    report of what the measure counted (``Measured.counts`` summed over the stage's groups)."""

    def pairs(ctx: StageContext) -> PairMeasure:
        return lambda g, rng: measure(g, rng, ctx.params)

    def prepared(ctx: StageContext) -> Prepare | None:
        return None if prepare is None else functools.partial(prepare, ctx)

    def run(ctx: StageContext) -> dict[str, Any]:
        return run_pair_measure(ctx, name, pairs(ctx), None if tolerance is None else tolerance(ctx.params),
                                prepared(ctx), summary)

    def finish(ctx: StageContext) -> dict[str, Any]:
        return attach_null_simulators(ctx, pairs(ctx), prepared(ctx))

    return family_stage("distance", name=name, version=version, params=params, run=run, description=description,
                        tiling="tile", finish=finish)


def euclidean(group: PairGroup, rng: np.random.Generator, scale: float = 1.0) -> MeasureResult:
    """The plain Euclidean (cloud-to-cloud) distance of each pair, times ``scale``; no p-value, exact."""
    return np.linalg.norm(group.mu_q - group.mu_r, axis=1) * scale, None, np.zeros(0)


def reference_cloud(reference: Composite, spacing: float, rng: np.random.Generator) -> np.ndarray:
    """The visible part of the composite as one point cloud: its visible points, its visible facets sampled about
    once per ``spacing``² (at least once each), item by item."""
    parts = [sample_surface(item.dataset, spacing, rng, np.flatnonzero(item.visible)) for item in reference.items]
    return np.concatenate(parts) if parts else np.zeros((0, 3))
