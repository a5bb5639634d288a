"""Running a plan: each epoch's inputs read, the chain run over a shared context, the composite written to the twin.

Reproducibility: every stage gets a numpy Generator from ``SeedSequence(workflow seed, spawn_key=(epoch, stage))``,
so the same workflow and inputs give the same twin whatever else runs. Traceability: every stage gets a cache key,
the sha256 of its plugin, name and version, validated params, the epoch's input digests and the keys upstream of it;
the keys and everything else needed to re-run an epoch go into the epoch's provenance and into ``gdt.lock``.

Safety: the twin is built in a temporary folder beside the target and moved into place only when every epoch has
been written, so a failure or an interrupt leaves an existing twin exactly as it was and no half-written one. The
move exchanges the two folders in one step (see ``twin_store.swap``); what a killed run left behind is put back or
cleaned up by the next run. ``GDT_FAULT`` (tests only) kills the process at a named step (``twin_store.faults``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import platform
import shutil
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from twin_store import RUN_LOCK_NAME, TwinStore, TwinStoreError, fault, writer_lock

from ..errors import GdtError
from ..memory import peak_rss_mb, return_freed_memory
from ..names import UNITS
from ..plugins import NullProgress, Progress, Registry, StageContext, StageSpec, TileExecutor, load_registry
from ..provenance import (
    EpochProvenance,
    EpochRecord,
    StageRecord,
    WorkflowRecord,
    cache_key,
    package_versions,
)
from ..tiling.grid import extent
from ..twin_elements import composite_to_elements
from ..twin_reference import stored_composite
from ..types import Composite, Dataset, EpochInfo
from ..workflow import load_workflow
from .history import Start, start_on
from .inputs import input_digests, read_input, relative_to_workflow
from .plan import EpochPlan, RunPlan, StagePlan, plan_from_workflow
from .run_record import add_epoch, input_record, plain, registration_record, start_record
from .stage_call import run_stage, stage_rng, stage_survey
from .staging import check_overwritable, recover, staging_path, swap_into_place, write_json_atomic
from .tiled import TileSession, TilingOptions, chain_runs, run_tiles, tileable

log = logging.getLogger("gdt.run")

LOCK_NAME = RUN_LOCK_NAME
# Slots kept to the end of an epoch whoever reads them: what the writer and the provenance use.
KEPT_SLOTS = frozenset({"composite", "rov", "registration", "epoch"})


@dataclass
class EpochSummary:
    """What one epoch produced, for the CLI and for tests."""

    id: str
    counts: dict[str, int]
    seconds: float
    layer: Path


@dataclass
class RunResult:
    """Where the run wrote its twin, and a summary per epoch."""

    twin: Path
    lock: Path
    epochs: list[EpochSummary] = field(default_factory=list)
    kept: list[str] = field(default_factory=list)  # the twin's epochs the run kept as they were (not re-run)
    replaced: list[str] = field(default_factory=list)  # the twin's epochs it rebuilt (``--from``)
    notes: list[str] = field(default_factory=list)  # what it took on trust (kept inputs whose files are gone)


class Reporter:
    """Hooks the CLI uses to show progress; the default shows nothing."""

    progress: Progress = NullProgress()

    def epoch_started(self, epoch: EpochPlan, index: int, total: int) -> None:
        """An epoch begins."""

    def stage_started(self, epoch: EpochPlan, index: int, spec: StageSpec) -> None:
        """A stage begins."""

    def stage_finished(self, epoch: EpochPlan, index: int, spec: StageSpec, seconds: float) -> None:
        """A stage ended."""

    def epoch_finished(self, summary: EpochSummary) -> None:
        """An epoch was written."""

    def executor_opened(self, name: str, executor: TileExecutor) -> None:
        """A tile executor started (its dashboard, when it has one, is worth showing)."""


@dataclass(frozen=True)
class _RunContext:
    """What every epoch of one run shares."""

    plan: RunPlan
    registry: Registry
    reporter: Reporter
    digests: dict[tuple[int, int], str]
    packages: dict[str, str]
    workflow: WorkflowRecord
    tiles: TileSession | None = None


def run_workflow(path: str | Path, *, registry: Registry | None = None, twin: str | Path | None = None,
                 overwrite: bool = False, from_epoch: str | None = None, reporter: Reporter | None = None,
                 tiling: TilingOptions | None = None) -> RunResult:
    """Run a workflow file and write its twin; return where it went. On an existing twin only the epochs it does
    not hold run (``from_epoch``: rebuild from that epoch on; ``overwrite``: rebuild all). ``tiling`` overrides the
    workflow's ``execution`` block."""
    registry = registry or load_registry()
    wf = load_workflow(path, registry, check_files=False)
    target = Path(twin).resolve() if twin is not None else wf.twin_path()
    wf = load_workflow(path, registry, held=held_epochs(target, overwrite, from_epoch))
    plan = plan_from_workflow(wf, registry)
    return execute_plan(plan, registry, target, overwrite=overwrite, from_epoch=from_epoch, reporter=reporter,
                        tiling=tiling if tiling is not None else plan.tiling)


def held_epochs(target: Path, overwrite: bool = False, from_epoch: str | None = None) -> frozenset[str]:
    """The epochs of the twin at ``target`` a run keeps at most, whose input files need not exist any more."""
    if overwrite or not (target / "twin.usda").is_file():
        return frozenset()
    try:
        held = TwinStore.open(target).epochs()
    except TwinStoreError:
        return frozenset()
    return frozenset(held[: held.index(from_epoch)] if from_epoch in held else held)


def execute_plan(plan: RunPlan, registry: Registry, target: Path, *, overwrite: bool = False,
                 from_epoch: str | None = None, append: bool = False, reporter: Reporter | None = None,
                 tiling: TilingOptions | None = None) -> RunResult:
    """Run a plan into the twin at ``target``, holding the twin's writer lock (``tiling``: cut epochs into tiles).
    On an existing twin, the epochs it holds that match the plan are kept and only the others run; ``append``
    keeps every epoch the twin holds, unchecked, and runs the plan's epochs after them (``gdt add``, audits)."""
    reporter = reporter or Reporter()
    target = Path(target).resolve()
    target.parent.mkdir(parents=True, exist_ok=True)
    tiles = None
    if tiling is not None and tiling.enabled:
        registry.executor(tiling.executor)  # an unknown executor fails before anything is read
        tiles = TileSession(tiling, registry, reporter.executor_opened)
    try:
        with writer_lock(target), contextlib.ExitStack() as stack:
            if tiles is not None:
                stack.enter_context(tiles.stack)
            return _run_locked(plan, registry, reporter, target, (overwrite, from_epoch, append), tiles)
    except TwinStoreError as exc:
        raise GdtError(str(exc)) from exc


def _start(plan: RunPlan, target: Path, overwrite: bool, from_epoch: str | None, append: bool) -> Start | None:
    """Where the run starts: None for a new twin (none there, or ``overwrite``), else the twin's epochs it keeps
    (``append``: all of them)."""
    recover(target)
    if target.exists() and not (target / "twin.usda").is_file():
        raise GdtError(f"{target} exists and is not a twin (no twin.usda); refusing to replace it")
    if append and not target.exists():
        raise GdtError(f"no twin at {target} to add an epoch to")
    if target.exists():
        check_overwritable(target, "--overwrite replaces" if overwrite else "a run on a twin rewrites")
    if not target.exists() or overwrite:
        if from_epoch is not None and from_epoch not in [e.id for e in plan.epochs]:
            raise GdtError(f"--from {from_epoch}: the workflow has no such epoch "
                           f"({', '.join(e.id for e in plan.epochs)})")
        return None
    store = TwinStore.open(target)
    store.verify()  # a twin that is not what was written is never built on
    return Start(kept=store.epochs()) if append else start_on(plan, store, from_epoch)


def _run_locked(plan: RunPlan, registry: Registry, reporter: Reporter, target: Path,
                mode: tuple[bool, str | None, bool], tiles: TileSession | None) -> RunResult:
    start = _start(plan, target, *mode)
    kept = [] if start is None else start.kept
    result = RunResult(twin=target, lock=target / LOCK_NAME, kept=list(kept),
                       replaced=[] if start is None else list(start.replaced),
                       notes=[] if start is None else list(start.notes))
    todo = [e for e in plan.epochs if e.index >= len(kept)] if start is None or not start.extra else []
    if start is not None and not todo:
        return result  # the twin holds every epoch of the workflow: nothing to run, nothing rewritten
    run = _RunContext(plan, registry, reporter, input_digests(plan, todo), package_versions(),
                      WorkflowRecord(path=relative_to_workflow(plan.workflow_path, plan.base_dir),
                                     sha256=plan.workflow_sha256, name=plan.name,
                                     dir_from_twin=os.path.relpath(plan.base_dir, target), units=plan.units,
                                     up_axis=plan.up_axis, text=plan.workflow_text), tiles)
    staging = staging_path(target)
    if staging.exists():
        shutil.rmtree(staging)
    try:
        if kept:
            store, copied = TwinStore.open(target).branch(staging, kept)
            if copied:
                log.warning("the filesystem cannot hard-link: %d layer files of the kept epochs were copied", copied)
        else:
            store = TwinStore.create(staging, meters_per_unit=UNITS[plan.units], up_axis=plan.up_axis, lock=False)
        lock = start_record(run.workflow, plan.seed, run.packages, target, store, kept)
        roles = {**{e.id: e.role for e in plan.epochs}, **_recorded_roles(store, kept)}
        composite = stored_composite(store, kept[-1], roles) if kept else None
        epoch_key = EpochProvenance.from_dict(store.provenance(kept[-1])).epoch_key if kept else None
        for epoch in todo:
            t_epoch = time.perf_counter()
            prov, slots = _run_epoch(run, epoch, composite, epoch_key)
            epoch_key, composite = prov.epoch_key, None
            summary = _write_epoch(store, prov, slots, target, time.perf_counter() - t_epoch)
            del slots  # this epoch's datasets, matches and scores must not stay alive through the next epoch
            if epoch is not todo[-1]:
                # what the next epoch sees is what the twin stores: the same whether it runs now or in an append
                composite = stored_composite(store, epoch.id, roles)
            result.epochs.append(summary)
            reporter.epoch_finished(summary)
            add_epoch(lock, prov)
        lock["layer_sha256"] = store.layer_digests()
        write_json_atomic(staging / LOCK_NAME, lock)
        fault("lock-written")
        fault("before-swap")
        swap_into_place(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return result


def _recorded_roles(store: TwinStore, epochs: list[str]) -> dict[str, str]:
    """The role each of the twin's epochs was run in (for sets written before the twin kept their own)."""
    return {eid: EpochProvenance.from_dict(store.provenance(eid)).epoch.role for eid in epochs}


def _run_epoch(run: _RunContext, epoch: EpochPlan, composite: Composite | None, epoch_key: str | None
               ) -> tuple[EpochProvenance, dict[str, Any]]:
    """Read the epoch's inputs and run its chain; its provenance and the slots the chain left."""
    plan = run.plan
    started = datetime.now(UTC).isoformat(timespec="seconds")
    run.reporter.epoch_started(epoch, epoch.index, len(plan.epochs))
    info = EpochInfo(id=epoch.id, index=epoch.index, role=epoch.role, seed=plan.seed, workflow_dir=plan.base_dir,
                     units=plan.units)
    digests = [run.digests[(epoch.index, i)] for i in range(len(epoch.inputs))]
    read = [read_input(plan, run.registry, epoch, i, digests[i]) for i in range(len(epoch.inputs))]
    inputs = [input_record(parts, poses, inp) for (parts, poses), inp in zip(read, epoch.inputs, strict=True)]
    recent = [ds for parts, _ in read for ds in parts]
    info = dataclasses.replace(info, origin=_frame_origin(recent))
    slots: dict[str, Any] = {"recent": recent, "epoch": info}
    del read, recent  # the slots alone hold the scans, so that a tiled run can move them to disk (tiling.point_file)
    if composite is not None:
        slots["reference"] = composite
    upstream = [epoch_key] if epoch_key else []
    records: list[StageRecord] = []
    runs = chain_runs(epoch.stages, run.tiles is not None)
    for k, stages in enumerate(runs):
        if (len(stages) == 1 and not tileable(stages[0])) or run.tiles is None:
            records.append(_run_chain_stage(run, epoch, stages[0], info, slots, digests, upstream))
        else:
            records += _run_tile_stages(run, epoch, stages, slots, digests, upstream)
        _drop_unread(slots, runs[k + 1:])
    prov = EpochProvenance(
        gdt_pipeline=run.packages.get("gdt-pipeline", "?"), workflow=run.workflow,
        epoch=EpochRecord(epoch.id, epoch.index, epoch.role), seed=plan.seed,
        inputs=inputs,
        stages=records, registration=registration_record(slots.get("registration")), packages=run.packages,
        python=platform.python_version(), started=started, finished=datetime.now(UTC).isoformat(timespec="seconds"),
        counts=_kept_retired(slots, composite).counts(), epoch_key=upstream[-1] if upstream else None)
    return prov, slots


def _kept_retired(slots: dict[str, Any], reference: Composite | None) -> Composite:
    """The epoch's composite with the retired sets of its reference (the twin keeps them; the stages never saw
    them), so that its counts are the whole twin's."""
    if reference is None or not reference.retired:
        return slots["composite"]
    slots["composite"] = dataclasses.replace(slots["composite"], retired=reference.retired)
    return slots["composite"]


def _drop_unread(slots: dict[str, Any], later: list[list[StagePlan]]) -> None:
    """Let go of the slots no later stage reads and the epoch's writer does not need (correspondences and scores
    after the threshold: a tenth of a kilobyte a point)."""
    wanted = KEPT_SLOTS | {s for run in later for st in run for s in (*st.spec.requires, *st.spec.optional)}
    unread = [n for n in slots if n not in wanted]
    for name in unread:
        del slots[name]
    if unread:  # else their pages stay in glibc's heap under the next stage's peak (memory.py)
        return_freed_memory()


def _run_chain_stage(run: _RunContext, epoch: EpochPlan, stage: StagePlan, info: EpochInfo, slots: dict[str, Any],
                     digests: list[str], upstream: list[str]) -> StageRecord:
    """Run one stage of the chain on the epoch's slots (updated in place); append its cache key to ``upstream``."""
    spec, s_index = stage.spec, stage.index
    rng, seed = stage_rng(run.plan.seed, epoch.index, s_index)
    where = f"epoch {epoch.id}, stage {s_index} {spec.name!r} ({spec.plugin} {spec.plugin_version})"
    visible = {k: v for k, v in slots.items() if k in spec.requires or k in spec.optional or k == "epoch"}
    run.reporter.stage_started(epoch, s_index, spec)
    t0 = time.perf_counter()
    ctx = StageContext(stage=spec, params=stage.params, slots=visible, epoch=info, rng=rng, seed=seed,
                       log=logging.getLogger(f"gdt.stage.{spec.name}"), progress=run.reporter.progress,
                       survey=stage_survey(spec, stage.params, visible, where))
    slots.update(run_stage(spec, ctx, where))
    # a stage's freed working arrays stay resident in glibc's heap (memory.py); the next stage starts without them
    return_freed_memory()
    dt = time.perf_counter() - t0
    run.reporter.stage_finished(epoch, s_index, spec, dt)
    return _stage_record(run, epoch, stage, digests, upstream, dt, ctx.notes)


def _run_tile_stages(run: _RunContext, epoch: EpochPlan, stages: list[StagePlan], slots: dict[str, Any],
                     digests: list[str], upstream: list[str]) -> list[StageRecord]:
    """Run a run of tileable stages tile by tile (``tiled``); one record per stage, its seconds summed over tiles."""
    assert run.tiles is not None
    for st in stages:
        run.reporter.stage_started(epoch, st.index, st.spec)
    names = "+".join(st.spec.name for st in stages)
    outcome = run_tiles(run.tiles, stages, slots, run.plan.seed,
                        lambda n: run.reporter.progress.task(f"{names}: tiles", total=n))
    records = []
    for st, dt, report in zip(stages, outcome.seconds, outcome.reports, strict=True):
        run.reporter.stage_finished(epoch, st.index, st.spec, dt)
        records.append(_stage_record(run, epoch, st, digests, upstream, dt, report))
    return records


def _stage_record(run: _RunContext, epoch: EpochPlan, stage: StagePlan, digests: list[str], upstream: list[str],
                  seconds: float, report: dict[str, Any]) -> StageRecord:
    """The provenance record of a stage that ran; its cache key is appended to ``upstream``."""
    spec, s_index = stage.spec, stage.index
    params = json.loads(stage.params.model_dump_json())
    _, seed = stage_rng(run.plan.seed, epoch.index, s_index)
    key = cache_key(spec, params, digests, upstream)
    # the process's peak RSS so far: where an epoch's memory goes, stage by stage (workers' own are not in it)
    peak_mb = round(peak_rss_mb(), 1)
    log.info("stage done", extra={"event": {"epoch": epoch.id, "stage": spec.name, "index": s_index,
                                            "seconds": round(seconds, 4), "cache_key": key, "peak_rss_mb": peak_mb}})
    upstream.append(key)
    return StageRecord(index=s_index, id=stage.id, uses=spec.name, family=spec.family, version=spec.version,
                       plugin=spec.plugin, plugin_version=spec.plugin_version, entry_point=spec.entry_point,
                       params=params, seed_spawn_key=[epoch.index, s_index], seed=seed,
                       requires=list(spec.requires), provides=list(spec.provides), cache_key=key,
                       seconds=round(seconds, 4), report=json.loads(json.dumps(report, default=plain)))


def _write_epoch(store: TwinStore, prov: EpochProvenance, slots: dict[str, Any], target: Path, seconds: float
                 ) -> EpochSummary:
    """Write the epoch's layer: the composite's elements, its provenance, region of view and segments."""
    composite: Composite = slots["composite"]
    rov = slots.get("rov")
    layer = store.write_epoch(prov.epoch.id, composite_to_elements(composite), prov.to_dict(),
                              None if rov is None else (rov.vertices, rov.faces), composite.segments)
    log.info("epoch written", extra={"event": {"epoch": prov.epoch.id, "layer": Path(layer).name,
                                               "peak_rss_mb": round(peak_rss_mb(), 1)}})
    return EpochSummary(prov.epoch.id, composite.counts(), seconds, target / "epochs" / Path(layer).name)


def _frame_origin(recent: list[Dataset]) -> tuple[float, float, float] | None:
    """The centre of the epoch's input data (rounded to 1 mm in metres): the origin its stages share."""
    if not any(len(ds.points) for ds in recent):
        return None
    lower, upper = extent([ds.points for ds in recent])
    centre = (lower + upper) / 2
    return (float(np.round(centre[0], 3)), float(np.round(centre[1], 3)), float(np.round(centre[2], 3)))
