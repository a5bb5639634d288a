"""Running runs of tileable stages one 3-D tile at a time (``docs/scale.md``).

The chain is cut into runs: a run of consecutive stages that declare ``tiling="tile"``, or one whole-epoch stage.
For a tile run the runner picks the halo (the sum of the stages' reaches: each stage needs the previous one's results
that far out), cuts the slots the run reads to every tile's box plus halo, hands the tiles to the executor, and
merges the core results back in element order (``tiling.merge``), checking that every element came from exactly one
tile. Then each stage's ``finish`` runs once on the merged slots. Whole-epoch stages (registration, the region of
view, calibration, fusion) see the merged slots as if the epoch had run whole.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import GdtError
from ..memory import return_freed_memory
from ..plugins import ExecutorOptions, Registry, StageContext, TileBounds, TileExecutor
from ..scratch import scratch_folder
from ..slots import valid
from ..tiling import (
    CandidateSink,
    CellIndex,
    ElementOrder,
    crop_composite,
    crop_rov,
    grid_for,
    lookup,
    members_of,
    merge_change,
    merge_correspondences,
    size_for_budget,
    take_candidates,
    take_dataset,
)
from ..tiling.crop import take_change, take_scores
from ..tiling.merge import RecentSink
from ..tiling.point_file import spilled_points
from ..tiling.score_sink import ScoreSink
from ..types import Composite, CompositeItem, Dataset
from .halos import StageReach, stage_reaches, tile_reaches
from .plan import StagePlan, TilingOptions
from .stage_call import stage_rng, stage_survey
from .tile_work import TileResult, TileStage, TileTask, run_tile

log = logging.getLogger("gdt.tiles")

MERGEABLE = frozenset({"recent", "correspondences", "scores", "change"})
# Per-tile reports kept in a stage's provenance; beyond this only their count.
KEPT_TILE_REPORTS = 16
# A tile whose neighbourhoods reached past its halo runs again with the halo grown by this times the shortfall, at
# most this many times.
HALO_GROWTH = 1.5
MAX_HALO_ROUNDS = 4


def tileable(st: StagePlan) -> bool:
    """Whether a stage may run tile by tile: it says so, and everything it provides can be merged."""
    return st.spec.tiling == "tile" and set(st.spec.provides) <= MERGEABLE


def chain_runs(stages: list[StagePlan], tiled: bool) -> list[list[StagePlan]]:
    """The chain cut into runs of tileable stages and single whole-epoch stages. A stage whose reach or survey
    depends on data starts a new run when it reads a slot the run already changes (both are measured on the run's
    input)."""
    runs: list[list[StagePlan]] = []
    current: list[StagePlan] = []
    provided: set[str] = set()
    for st in stages:
        if not (tiled and tileable(st)):
            runs += [current, [st]] if current else [[st]]
            current, provided = [], set()
            continue
        measured = st.spec.reach is not None or st.spec.survey is not None
        if current and measured and provided & set(st.spec.requires):
            runs.append(current)
            current, provided = [], set()
        current.append(st)
        provided |= set(st.spec.provides)
    return runs + ([current] if current else [])


@dataclass
class TileSession:
    """One run's tiling: the options, the executor (opened at the first tile run, closed with the run) and each
    epoch's tile size (fixed at its first tile run, so that all its runs share one grid)."""

    options: TilingOptions
    registry: Registry
    on_open: Callable[[str, TileExecutor], None] = lambda name, ex: None
    stack: contextlib.ExitStack = field(default_factory=contextlib.ExitStack)
    sizes: dict[str, float] = field(default_factory=dict)
    _executor: TileExecutor | None = None

    def __post_init__(self) -> None:
        self.sizes.update(dict(self.options.epoch_sizes))

    def executor(self) -> tuple[TileExecutor, Callable[[TileTask], TileResult]]:
        """The open executor and the function it runs per tile."""
        spec = self.registry.executor(self.options.executor)
        if self._executor is None:
            opts = ExecutorOptions(workers=self.options.workers, address=self.options.address)
            self._executor = self.stack.enter_context(spec.open(opts))
            self.on_open(spec.name, self._executor)
        fn = functools.partial(run_tile, registry=self.registry) if spec.in_process else run_tile
        return self._executor, fn

    def worker_threads(self) -> int | None:
        """Compiled-kernel threads per worker, so that workers × threads fill the cores without oversubscribing."""
        if self.registry.executor(self.options.executor).in_process:
            return None
        return max(1, (os.cpu_count() or 1) // max(1, self.options.workers or (os.cpu_count() or 1)))


@dataclass
class TileRunOutcome:
    """Per stage of a tile run: its summed seconds over tiles and its report."""

    seconds: list[float]
    reports: list[dict[str, Any]]


@dataclass
class _Cutter:
    """Cuts an epoch's slots to one tile: the grid, each tile's core members and box indexes of the big sets."""

    slots: dict[str, Any]
    reads: set[str]
    reaches: list[StageReach]
    size: float
    surveys: dict[int, dict[str, Any]] = field(default_factory=dict)  # per stage index, its whole-epoch figures

    def __post_init__(self) -> None:
        recent: list[Dataset] = self.slots["recent"]
        positions = [ds.element_positions() for ds in recent]
        self.grid = grid_for(positions, self.size)
        self.recent_index = [CellIndex(self.grid, p) for p in positions]
        self.members = members_of(self.recent_index)
        self.stage_reach = {t: tile_reaches(self.reaches, *self.grid.bounds(t), self.recent_index)
                            for t in self.members}
        ref: Composite | None = self.slots.get("reference")
        # Meshes stay whole in every tile: where CAD surfaces touch (a part standing on the floor), Open3D resolves a
        # tie between them by its BVH's traversal, which depends on the facets it holds; a tile holding other facets
        # than the epoch would pick the other surface. CAD is small next to scans; point items are cut.
        self.ref_finders = None if ref is None else [
            CellIndex(self.grid, it.dataset.points).query if it.dataset.faces is None else _everything(it)
            for it in ref.items]

    def halo(self, tile: int) -> float:
        """The halo tile ``tile`` needs: the sum of its stages' reaches (each needs the previous one's results)."""
        return float(sum(self.stage_reach[tile]))

    def later_reach(self, tile: int) -> tuple[float, ...]:
        """Per stage, how far around the core its results must hold in tile ``tile``: the later stages' reach."""
        reach = self.stage_reach[tile]
        return tuple(float(sum(reach[k + 1:])) for k in range(len(reach)))

    def task(self, tile: int, stages: list[StagePlan], seed: int, threads: int | None, halo: float | None = None
             ) -> TileTask:
        """The task of tile ``tile`` (with a wider ``halo`` than its own when a first try fell short)."""
        lo, hi = self.grid.bounds(tile)
        halo = self.halo(tile) if halo is None else halo
        blo, bhi = lo - halo, hi + halo
        recent: list[Dataset] = self.slots["recent"]
        ids = [index.query(blo, bhi) for index in self.recent_index]
        core = [np.searchsorted(i, m) for i, m in zip(ids, self.members[tile], strict=True)]
        cut: dict[str, Any] = {k: v for k, v in self.slots.items() if k in self.reads or k == "epoch"}
        cut["recent"] = [take_dataset(ds, i) for ds, i in zip(recent, ids, strict=True)]
        candidate_ids, extra = self._cut_correspondences(cut, ids)
        keeps: list[np.ndarray] = []
        if "reference" in self.slots:
            ref, keeps = crop_composite(self.slots["reference"], blo, bhi, extra, self.ref_finders)
            cut["reference"] = ref
            if "rov" in cut:
                cut["rov"] = crop_rov(cut["rov"], keeps, [it.key for it in ref.items])
        for name, take in (("scores", take_scores), ("change", take_change)):
            if name in cut:
                cut[name] = [take(x, ids[x.query]) for x in cut[name]]
        provides = tuple(sorted({s for st in stages for s in st.spec.provides}))
        return TileTask(tile=tile, seed=seed, epoch=self.slots["epoch"], stages=tuple(
            TileStage(st.spec.name, st.index, json.loads(st.params.model_dump_json()), self.surveys.get(st.index, {}))
            for st in stages),
            slots=cut, recent_ids=ids, core=core, n_elements=[ds.n_elements for ds in recent], ref_keeps=keeps,
            provides=provides, candidate_ids=candidate_ids, threads=threads,
            bounds=TileBounds(lo, hi, blo, bhi), later_reach=self.later_reach(tile))

    def _cut_correspondences(self, cut: dict[str, Any], ids: list[np.ndarray]
                             ) -> tuple[list[np.ndarray] | None, dict[int, np.ndarray]]:
        """Correspondences made before the tile run, cut to the tile's elements; the reference elements they name
        are kept in the reference crop whatever the halo."""
        if "correspondences" not in cut:
            return None, {}
        extra: dict[int, list[np.ndarray]] = {}
        candidate_ids, pieces = [], []
        for corr in cut["correspondences"]:
            local = lookup(ids[corr.query])(corr.element)
            keep = local >= 0
            candidate_ids.append(np.flatnonzero(keep))
            for item in np.unique(corr.ref_item[keep & corr.found]):
                extra.setdefault(int(item), []).append(corr.ref_element[keep & (corr.ref_item == item)])
            pieces.append((corr, keep))
        # renumbered once the reference crop (box + these elements) is known: _finish_correspondences
        cut["correspondences_pending"] = pieces
        return candidate_ids, {i: np.unique(np.concatenate(v)) for i, v in extra.items()}


def _everything(item: CompositeItem) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    n = item.dataset.n_elements
    return lambda lower, upper: np.arange(n)


def _finish_correspondences(task: TileTask) -> TileTask:
    """Renumber cut-in correspondences to the tile's crop (their reference elements are in it by construction)."""
    pending = task.slots.pop("correspondences_pending", None)
    if pending is None:
        return task
    ref_maps = [lookup(keep) for keep in task.ref_keeps]
    task.slots["correspondences"] = [
        take_candidates(corr, keep, lookup(task.recent_ids[corr.query]), ref_maps, len(task.recent_ids[corr.query]))
        for corr, keep in pending]
    return task


def _merge(slots: dict[str, Any], members: dict[int, list[np.ndarray]], results: list[TileResult],
           provides: set[str], sink: RecentSink, candidates: CandidateSink | None, scores: ScoreSink
           ) -> dict[str, Any]:
    """The tiles' core results merged into whole-epoch slots (``sink``: the uncertainty merged as tiles finished;
    ``candidates``: their candidates, when kept on disk as they finished; ``scores``: their scores, put in place as
    they finished)."""
    recent: list[Dataset] = slots["recent"]
    tiles = [r.tile for r in results]
    orders = [ElementOrder.check(ds.name, [members[t][d] for t in tiles], ds.n_elements)
              for d, ds in enumerate(recent)]
    out: dict[str, Any] = {}
    if "recent" in provides:
        out["recent"] = [sink.merged(ds, d, [r.slots["recent"][d] for r in results], [members[t][d] for t in tiles],
                                     orders[d]) for d, ds in enumerate(recent)]
    maps: dict[int, list[np.ndarray]] = {}
    if "correspondences" in provides:
        merged = []
        for d, ds in enumerate(recent):
            if candidates is not None:
                corr, maps[d] = candidates.merged(d, tiles, ds.n_elements)
                merged.append(corr)
                continue
            pieces = [r.slots["correspondences"][d] for r in results]
            for r in results:  # the merge lets go of each tile's candidates as it places them
                r.slots["correspondences"][d] = None
            corr, maps[d] = merge_correspondences(pieces, ds.n_elements, d, release=True)
            merged.append(corr)
        out["correspondences"] = merged
    if "scores" in provides:
        out["scores"] = [scores.merged(d, tiles, [members[t][d] for t in tiles], maps.get(d))
                         for d in range(len(recent))]
    if "change" in provides:
        out["change"] = [merge_change([r.slots["change"][d] for r in results], orders[d]) for d in range(len(recent))]
    for r in results:  # merged: the tiles' pieces go before the stages' finish runs on the merged slots
        r.slots.clear()
    return_freed_memory()
    return out


def run_tiles(session: TileSession, stages: list[StagePlan], slots: dict[str, Any], seed: int,
              progress_task: Callable[[int], contextlib.AbstractContextManager[Callable[[], None]]]) -> TileRunOutcome:
    """Run ``stages`` tile by tile on ``slots`` (updated in place with the merged results)."""
    reads = {s for st in stages for s in (*st.spec.requires, *st.spec.optional)}
    reaches = stage_reaches(stages, slots)
    epoch_id = slots["epoch"].id
    folder = scratch_folder() if session.options.spill else None
    if folder is not None:  # from here on the scans are read a gather of rows at a time (tiling.point_file)
        slots["recent"] = [spilled_points(ds, folder) for ds in slots["recent"]]
    if epoch_id not in session.sizes:  # one size per epoch: its data decide it when a budget is given
        positions = [ds.element_positions() for ds in slots["recent"]]
        session.sizes[epoch_id] = session.options.tile or size_for_budget(
            positions, int(session.options.max_elements or 1))
    surveys = {st.index: stage_survey(st.spec, st.params, slots, f"stage {st.index} {st.spec.name!r}")
               for st in stages if st.spec.survey is not None}
    cutter = _Cutter(slots, reads, reaches, session.sizes[epoch_id], surveys)
    return_freed_memory()  # the cut read every position: their pages go back to the page cache
    executor, fn = session.executor()
    threads = session.worker_threads()
    halos = [cutter.halo(t) for t in cutter.members]
    log.info("tiles: %d of %.4g with halos of %.4g to %.4g for %s", len(cutter.members), cutter.size,
             min(halos, default=0.0), max(halos, default=0.0), ", ".join(st.spec.name for st in stages))
    provides = {s for st in stages for s in st.spec.provides}
    sizes = [ds.n_elements for ds in slots["recent"]]
    sink = RecentSink(sizes, folder)
    scores = ScoreSink(sizes, folder)
    spill = "correspondences" in provides and session.options.spill
    with CandidateSink() if spill else contextlib.nullcontext() as candidates:

        def finished(result: TileResult) -> None:
            if "recent" in provides:
                sink.absorb(result.slots["recent"], cutter.members[result.tile])
            if candidates is not None:
                candidates.absorb(result.tile, result.slots["correspondences"])
            if "scores" in provides:
                scores.absorb(result.tile, result.slots["scores"], cutter.members[result.tile])

        with progress_task(len(cutter.members)) as advance:
            results = _run_rounds(cutter, list(cutter.members), executor, fn, stages, seed, threads, advance,
                                  finished)
        ordered = [results[t] for t in cutter.members]
        slots.update(_merge(slots, cutter.members, ordered, provides, sink, candidates, scores))
    _finish(stages, slots, seed)
    widened = sum(1 for r in ordered if r.halo > cutter.halo(r.tile))
    return _outcome(stages, ordered, cutter, session, widened)


def _run_rounds(cutter: _Cutter, tiles: list[int], executor: TileExecutor, fn: Callable[[TileTask], TileResult],
                stages: list[StagePlan], seed: int, threads: int | None, advance: Callable[[], None],
                finished: Callable[[TileResult], None]) -> dict[int, TileResult]:
    """Every tile's result, with halos widened where a stage's neighbourhoods reached past them.

    The first tile runs alone: what it falls short by widens every other tile's halo before they start, so a stage
    with k-nearest neighbourhoods (which declares no reach) costs one extra tile, not a second pass over all."""
    halos = {t: cutter.halo(t) for t in tiles}
    results: dict[int, TileResult] = {}

    def run(todo: list[int]) -> list[TileResult]:
        tasks = (_finish_correspondences(cutter.task(t, stages, seed, threads, halos[t])) for t in todo)

        def done(i: int, result: TileResult) -> None:
            if result.shortfall == 0:
                finished(result)
                advance()

        out = executor.map(fn, tasks, done)
        for r in out:
            r.halo = halos[r.tile]
            if r.shortfall == 0:
                results[r.tile] = r
        return [r for r in out if r.shortfall > 0]

    short = run(tiles[:1])
    if short:
        extra = HALO_GROWTH * short[0].shortfall
        halos = {t: h + extra for t, h in halos.items()}
    todo = [r.tile for r in short] + tiles[1:]
    for _ in range(MAX_HALO_ROUNDS):
        if not todo:
            return results
        short = run(todo)
        for r in short:  # a stage's neighbourhoods reached past the halo: that tile again, with room to spare
            halos[r.tile] += HALO_GROWTH * r.shortfall + 1e-9 * cutter.size
        todo = [r.tile for r in short]
    if todo:
        raise GdtError(f"tiles {todo[:5]}: neighbourhoods still reach past a halo widened {MAX_HALO_ROUNDS} times")
    return results


def _finish(stages: list[StagePlan], slots: dict[str, Any], seed: int) -> None:
    """Each stage's ``finish`` on the merged slots (e.g. a null simulator over every pair of the epoch)."""
    epoch = slots["epoch"]
    for st in stages:
        if st.spec.finish is None:
            continue
        rng, stage_seed = stage_rng(seed, epoch.index, st.index)
        visible = {k: v for k, v in slots.items()
                   if k in st.spec.requires or k in st.spec.optional or k in st.spec.provides or k == "epoch"}
        ctx = StageContext(stage=st.spec, params=st.params, slots=visible, epoch=epoch, rng=rng, seed=stage_seed,
                           log=logging.getLogger(f"gdt.stage.{st.spec.name}"))
        out = dict(st.spec.finish(ctx))
        for name, value in out.items():
            if name not in st.spec.provides or not valid(name, value):
                raise GdtError(f"stage {st.spec.name!r}: finish returned {name!r}, which it does not provide")
        slots.update(out)


def _outcome(stages: list[StagePlan], results: list[TileResult], cutter: _Cutter, session: TileSession,
             widened: int) -> TileRunOutcome:
    seconds = [float(sum(r.seconds[k] for r in results)) for k in range(len(stages))]
    halos = [r.halo for r in results]
    tiling = {"tiles": len(cutter.members), "tile_size": cutter.size, "halo": max(halos, default=0.0),
              "halo_median": float(np.median(halos)) if halos else 0.0,
              "tiles_with_wider_halo": widened,
              "executor": session.options.executor, "workers": session.options.workers}
    reports = []
    for k in range(len(stages)):
        per_tile = [{"tile": r.tile, "elements": r.elements, **r.reports[k]} for r in results[:KEPT_TILE_REPORTS]]
        # what every tile reported alike (a whole-epoch figure from the stage's survey) is the stage's, as in a
        # whole run
        first = results[0].reports[k] if results else {}
        alike = {key: value for key, value in first.items() if all(r.reports[k].get(key) == value for r in results)}
        reports.append({**alike, "tiling": tiling, "tile_reports": per_tile})
    return TileRunOutcome(seconds, reports)
