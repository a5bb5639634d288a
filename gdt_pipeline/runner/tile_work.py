"""One tile's work, wherever it runs: its stages in order on the tile's slots, then its core results in the epoch's
numbering. ``run_tile`` is what executors call; in another process it finds the stages through that process's own
registry (so every plugin must be installed where the workers run)."""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..plugins import NullProgress, Registry, StageContext, TileBounds, load_registry
from ..tiling.crop import IndexMap, take_candidates, take_change, take_scores
from ..tiling.merge import UncertaintyPiece
from ..types import EpochInfo
from .stage_call import run_stage, stage_rng

_REGISTRY: Registry | None = None


@dataclass(frozen=True)
class TileStage:
    """A stage as a tile task names it: by name, with its params as JSON (models built at run time don't pickle)."""

    name: str
    index: int
    params: dict[str, Any]
    survey: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class TileTask:
    """Everything one tile needs: its slots cut to the tile and halo, and how to map results back.

    ``recent_ids[d]``: sorted epoch indices of dataset d's elements in the crop; ``core[d]``: crop indices of those
    in the tile's core; ``ref_keeps[i]``: epoch indices of reference item i's elements in the crop;
    ``candidate_ids[d]``: epoch numbers of the candidates cut in, when correspondences came from outside the tile run.
    """

    tile: int
    seed: int
    epoch: EpochInfo
    stages: tuple[TileStage, ...]
    slots: dict[str, Any]
    recent_ids: list[np.ndarray]
    core: list[np.ndarray]
    n_elements: list[int]
    ref_keeps: list[np.ndarray]
    provides: tuple[str, ...]
    candidate_ids: list[np.ndarray] | None = None
    threads: int | None = None
    bounds: TileBounds | None = None
    later_reach: tuple[float, ...] = ()  # per stage, the reach of the stages after it in the run


@dataclass
class TileResult:
    """What a tile hands back: per provided slot its core results in epoch numbering, and per stage its report and
    seconds."""

    tile: int
    slots: dict[str, list[Any]]
    reports: list[dict[str, Any]] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    elements: int = 0
    shortfall: float = 0.0  # how much wider the halo must be (a stage's neighbourhoods reached past it)
    halo: float = 0.0  # the halo the tile ran with (set by the runner)


def _registry() -> Registry:
    global _REGISTRY
    if _REGISTRY is None:
        _REGISTRY = load_registry()
    return _REGISTRY


def _set_threads(threads: int | None) -> None:
    if not threads:
        return
    import numba

    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))


def run_tile(task: TileTask, registry: Registry | None = None) -> TileResult:
    """Run a tile's stages on its slots and return its core results (``registry``: this process's, in process)."""
    if registry is None:
        registry = _registry()
        _set_threads(task.threads)
    slots = dict(task.slots)
    reports, seconds, shortfall = [], [], 0.0
    for k, st in enumerate(task.stages):
        spec = registry.get(st.name)
        params = spec.params.model_validate(st.params)
        rng, seed = stage_rng(task.seed, task.epoch.index, st.index, task.tile)
        visible = {k: v for k, v in slots.items() if k in spec.requires or k in spec.optional or k == "epoch"}
        ctx = StageContext(stage=spec, params=params, slots=visible, epoch=task.epoch, rng=rng, seed=seed,
                           log=logging.getLogger(f"gdt.stage.{spec.name}"), progress=NullProgress(),
                           tile=_widened(task.bounds, task.later_reach[k] if task.later_reach else 0.0),
                           survey=st.survey)
        t0 = time.perf_counter()
        slots.update(run_stage(spec, ctx, f"epoch {task.epoch.id}, stage {st.index} {spec.name!r}, tile {task.tile}"))
        seconds.append(time.perf_counter() - t0)
        reports.append(dict(ctx.notes))
        shortfall = max([shortfall, *ctx.shortfalls])
    if shortfall > 0:  # the results are not the epoch's: the runner runs this tile again with a wider halo
        return TileResult(task.tile, {}, reports, seconds, shortfall=shortfall)
    return TileResult(task.tile, core_results(task, slots), reports, seconds,
                      elements=int(sum(len(c) for c in task.core)))


def _widened(bounds: TileBounds | None, reach: float) -> TileBounds | None:
    """The bounds a stage's neighbourhoods are checked against: its results must hold out to the later stages'
    reach around the core."""
    if bounds is None or reach == 0:
        return bounds
    return dataclasses.replace(bounds, core_lower=bounds.core_lower - reach, core_upper=bounds.core_upper + reach)


def core_results(task: TileTask, slots: dict[str, Any]) -> dict[str, list[Any]]:
    """The provided slots restricted to the tile's core elements, in the epoch's numbering."""
    out: dict[str, list[Any]] = {}
    if "recent" in task.provides:
        out["recent"] = [UncertaintyPiece(None if ds.uncertainty is None else ds.uncertainty.take(core), len(core))
                         for ds, core in zip(slots["recent"], task.core, strict=True)]
    kept_at: dict[int, np.ndarray] = {}
    if "correspondences" in task.provides:
        ref_maps = [_indexer(keep) for keep in task.ref_keeps]
        pieces = []
        for corr in slots["correspondences"]:
            d = corr.query
            in_core = np.zeros(len(task.recent_ids[d]), dtype=bool)
            in_core[task.core[d]] = True
            keep = in_core[corr.element]
            pieces.append(take_candidates(corr, keep, _indexer(task.recent_ids[d]), ref_maps, task.n_elements[d]))
            kept_at[d] = np.cumsum(keep) - 1
        out["correspondences"] = pieces
    if "scores" in task.provides:
        out["scores"] = [take_scores(s, task.core[s.query], _match_map(task, kept_at, s.query))
                         for s in slots["scores"]]
    if "change" in task.provides:
        out["change"] = [take_change(c, task.core[c.query]) for c in slots["change"]]
    return out


def _indexer(table: np.ndarray) -> IndexMap:
    return lambda idx: table[idx]


def _match_map(task: TileTask, kept_at: dict[int, np.ndarray], d: int) -> IndexMap | None:
    if d in kept_at:
        return _indexer(kept_at[d])
    if task.candidate_ids is not None:
        return _indexer(task.candidate_ids[d])
    return None

