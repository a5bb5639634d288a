"""The runner: reads each epoch's inputs, runs the chain over a shared context, and writes the composite to the twin.

Reproducibility: every stage gets a numpy Generator from ``SeedSequence(workflow seed, spawn_key=(epoch, stage))``,
so the same workflow and inputs give the same twin whatever else runs. Traceability: every stage gets a cache key,
the sha256 of its plugin, name and version, validated params, the epoch's input digests and the keys upstream of it;
the keys and everything else needed to re-run an epoch go into the epoch's provenance and into ``gdt.lock``.

Safety: the twin is built in a temporary folder beside the target and moved into place only when every epoch has
been written, so a failure or an interrupt leaves an existing twin exactly as it was and no half-written one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import platform
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np

from twin_store import TwinStore, TwinStoreError, writer_lock

from .errors import GdtError, InputError, StageError
from .names import UNITS, identifier
from .plugins import NullProgress, Progress, ReadRequest, Registry, StageContext, StageSpec, load_registry
from .twin import composite_to_elements
from .types import (
    Change,
    Composite,
    Correspondences,
    Dataset,
    EpochInfo,
    Registration,
    Scores,
    SourceInfo,
)
from .workflow import LoadedWorkflow, iter_chain, load_workflow

log = logging.getLogger("gdt.run")

LOCK_NAME = "gdt.lock"
PACKAGES = ("gdt-pipeline", "numpy", "scipy", "open3d-cpu", "open3d", "usd-core", "trimesh", "pydantic", "pluggy",
            "pymeshlab", "laspy")

# Types of the slots the engine knows; slots a third party invents are passed through unchecked.
SLOT_TYPES: dict[str, Callable[[Any], bool]] = {
    "recent": lambda v: isinstance(v, list | tuple) and all(isinstance(d, Dataset) for d in v),
    "registration": lambda v: isinstance(v, Registration),
    "correspondences": lambda v: isinstance(v, list | tuple) and all(isinstance(c, Correspondences) for c in v),
    "scores": lambda v: isinstance(v, list | tuple) and all(isinstance(c, Scores) for c in v),
    "change": lambda v: isinstance(v, list | tuple) and all(isinstance(c, Change) for c in v),
    "composite": lambda v: isinstance(v, Composite),
    "dataset": lambda v: isinstance(v, Dataset),
}


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    """sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def cache_key(spec: StageSpec, params: Mapping[str, Any], input_digests: list[str], upstream: list[str]) -> str:
    """sha256 of plugin, stage name and version, validated params, input digests and upstream keys."""
    payload = {"plugin": spec.plugin, "plugin_version": spec.plugin_version, "stage": spec.name,
               "version": spec.version, "params": params, "inputs": input_digests, "upstream": upstream}
    return hashlib.sha256(_canonical(payload).encode()).hexdigest()


def package_versions() -> dict[str, str]:
    """Versions of the packages that shape results."""
    out = {}
    for name in PACKAGES:
        with contextlib.suppress(PackageNotFoundError):
            out[name] = version(name)
    return out


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


def _rel(path: Path, base: Path) -> str:
    """A path relative to the workflow folder when below it (host-independent provenance), else absolute."""
    try:
        return path.resolve().relative_to(base.resolve()).as_posix()
    except ValueError:
        return str(path.resolve())


def _check_dataset(ds: Dataset, where: str) -> None:
    if ds.n_elements == 0 or len(ds.points) == 0:
        raise InputError(f"{where}: the {'mesh has no faces' if ds.faces is not None else 'point cloud is empty'}")
    bad = ~np.isfinite(ds.points).all(axis=1)
    if bad.any():
        first = np.flatnonzero(bad)[:5].tolist()
        raise InputError(f"{where}: {int(bad.sum())} of {len(ds.points)} coordinates are NaN or infinite "
                         f"(first rows {first}); clean the file or remove those points")


@dataclass(frozen=True)
class InputPlan:
    """One input to read: where, as what, in which units, and (for audits) the digest it must have."""

    path: Path
    name: str
    kind: str | None = None
    reader: str | None = None
    units: str = "m"
    viewpoints: list | None = None
    sha256: str | None = None


@dataclass(frozen=True)
class StagePlan:
    """One stage to run in an epoch: its position in the chain, record and validated params."""

    index: int
    spec: StageSpec
    params: Any
    id: str | None = None


@dataclass(frozen=True)
class EpochPlan:
    """One epoch to run."""

    id: str
    index: int
    role: str
    inputs: list[InputPlan]
    stages: list[StagePlan]


@dataclass(frozen=True)
class RunPlan:
    """Everything a run needs, from a workflow file or from a twin's recorded provenance (audits)."""

    name: str
    workflow_path: Path
    workflow_sha256: str
    base_dir: Path
    seed: int
    units: str
    up_axis: str
    epochs: list[EpochPlan]


def plan_from_workflow(wf: LoadedWorkflow, registry: Registry) -> RunPlan:
    """The run plan a validated workflow describes."""
    model = wf.model
    epochs = []
    for e_index, epoch in enumerate(model.epochs):
        inputs = [InputPlan(path=wf.input_path(inp), name=inp.name or identifier(Path(inp.path).stem), kind=inp.kind,
                            reader=inp.reader, units=inp.units or model.units, viewpoints=inp.viewpoints)
                  for inp in epoch.inputs]
        stages = [StagePlan(index=s_index, spec=registry.get(entry.uses), params=entry.with_, id=entry.id)
                  for s_index, entry in iter_chain(wf, epoch)]
        epochs.append(EpochPlan(id=epoch.id, index=e_index, role=epoch.role, inputs=inputs, stages=stages))
    return RunPlan(name=model.name, workflow_path=wf.path, workflow_sha256=wf.sha256, base_dir=wf.dir,
                   seed=model.seed, units=model.units, up_axis=model.up_axis, epochs=epochs)


def read_dataset(path: Path, registry: Registry, *, name: str, role: str = "as-is", kind: str | None = None,
                 reader: str | None = None, digest: str = "", where: str | None = None) -> Dataset:
    """Read one file with the reader its extension (or ``reader``) selects, and check the geometry is usable."""
    where = where or str(path)
    if reader:
        spec = registry.get(reader, family="reader")
    else:
        cands = registry.readers_for(path, kind)
        if not cands:
            raise InputError(f"{where}: no installed reader accepts this file")
        spec = cands[0]
    ctx = StageContext(stage=spec, params=spec.params(), epoch=EpochInfo("", -1, role, 0, path.parent),  # type: ignore[arg-type]
                       slots={"request": ReadRequest(path, name, role, kind, digest)},
                       rng=np.random.default_rng(0), seed=0, log=logging.getLogger(f"gdt.stage.{spec.name}"))
    try:
        ds = spec.run(ctx)["dataset"]
    except GdtError as exc:
        raise InputError(f"{where}: {exc}") from exc
    except Exception as exc:
        raise InputError(f"{where}: reader {spec.name!r} failed: {type(exc).__name__}: {exc}") from exc
    if not isinstance(ds, Dataset):
        raise StageError(f"{where}: reader {spec.name!r} returned {type(ds).__name__}, not a Dataset")
    _check_dataset(ds, where)
    return dataclasses.replace(ds, source=SourceInfo(path=str(path), sha256=digest, reader=spec.name))


def _read_input(plan: RunPlan, registry: Registry, epoch: EpochPlan, i_index: int, digest: str) -> Dataset:
    inp = epoch.inputs[i_index]
    ds = read_dataset(inp.path, registry, name=inp.name, role=epoch.role, kind=inp.kind, reader=inp.reader,
                      digest=digest, where=f"epoch {epoch.id}, input {i_index} ({inp.path})")
    scale = UNITS[inp.units] / UNITS[plan.units]
    vps = None if inp.viewpoints is None else np.asarray(inp.viewpoints, dtype=np.float64) * scale
    return dataclasses.replace(
        ds, points=ds.points * scale if scale != 1.0 else ds.points, viewpoints=vps,
        source=SourceInfo(path=_rel(inp.path, plan.base_dir), sha256=digest, units=inp.units, scale=scale,
                          reader=ds.source.reader if ds.source else ""))


def _run_stage(spec: StageSpec, ctx: StageContext, where: str) -> dict[str, Any]:
    try:
        out = spec.run(ctx)
    except GdtError as exc:
        raise type(exc)(f"{where}: {exc}") from exc
    except (KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:
        raise StageError(f"{where} failed: {type(exc).__name__}: {exc}") from exc
    if not isinstance(out, Mapping):
        raise StageError(f"{where} returned {type(out).__name__}, not a mapping of slots")
    got, want = set(out), set(spec.provides)
    if got != want:
        raise StageError(f"{where} broke its contract: it declares {sorted(want)} but returned {sorted(got)}")
    for slot, value in out.items():
        check = SLOT_TYPES.get(slot)
        if check is not None and not check(value):
            raise StageError(f"{where} returned a {type(value).__name__} for slot {slot!r}")
    return dict(out)


def _stage_rng(seed: int, epoch_index: int, stage_index: int) -> tuple[np.random.Generator, int]:
    ss = np.random.SeedSequence(seed, spawn_key=(epoch_index, stage_index))
    return np.random.default_rng(ss), int(ss.generate_state(1, dtype=np.uint32)[0])


def run_workflow(path: str | Path, *, registry: Registry | None = None, twin: str | Path | None = None,
                 overwrite: bool = False, reporter: Reporter | None = None) -> RunResult:
    """Run a workflow file end to end and write its twin; return where it went."""
    registry = registry or load_registry()
    wf = load_workflow(path, registry)
    target = Path(twin).resolve() if twin is not None else wf.twin_path()
    return execute_plan(plan_from_workflow(wf, registry), registry, target, overwrite=overwrite, reporter=reporter)


def execute_plan(plan: RunPlan, registry: Registry, target: Path, *, overwrite: bool = False,
                 reporter: Reporter | None = None) -> RunResult:
    """Run a plan into the twin at ``target``, holding the twin's writer lock."""
    reporter = reporter or Reporter()
    target = Path(target).resolve()
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        with writer_lock(target):
            return _run_locked(plan, registry, reporter, target, overwrite)
    except TwinStoreError as exc:
        raise GdtError(str(exc)) from exc


def _remove_stale_staging(target: Path) -> None:
    """Remove partial twins of runs that were killed (their process is gone); a live run holds the lock anyway."""
    for stale in target.parent.glob(f".{target.name}.partial-*"):
        pid = stale.name.rsplit("-", 1)[-1]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(stale, ignore_errors=True)
            log.info("removed the partial twin of an interrupted run: %s", stale)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _run_locked(plan: RunPlan, registry: Registry, reporter: Reporter, target: Path,
                overwrite: bool) -> RunResult:
    _remove_stale_staging(target)
    if target.exists() and not overwrite:
        raise GdtError(f"twin {target} already exists; pass --overwrite to replace it (the old twin stays intact "
                       f"until the new one is complete)")
    if target.exists() and not (target / "twin.usda").is_file():
        raise GdtError(f"{target} exists and is not a twin (no twin.usda); refusing to replace it")

    digests: dict[tuple[int, int], str] = {}
    for epoch in plan.epochs:
        for i_index, inp in enumerate(epoch.inputs):
            try:
                digests[(epoch.index, i_index)] = sha256_file(inp.path)
            except OSError as exc:
                raise InputError(f"epoch {epoch.id}, input {i_index} ({inp.path}): cannot read: "
                                 f"{exc.strerror}") from exc

    staging = target.parent / f".{target.name}.partial-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    packages = package_versions()
    workflow_record = {"path": _rel(plan.workflow_path, plan.base_dir), "sha256": plan.workflow_sha256,
                       "name": plan.name, "dir_from_twin": os.path.relpath(plan.base_dir, target),
                       "units": plan.units, "up_axis": plan.up_axis}
    lock: dict[str, Any] = {"format": 1, "workflow": workflow_record, "seed": plan.seed, "packages": packages,
                            "epochs": []}
    result = RunResult(twin=target, lock=target / LOCK_NAME)
    try:
        store = TwinStore.create(staging, meters_per_unit=UNITS[plan.units], up_axis=plan.up_axis, lock=False)
        composite: Composite | None = None
        upstream_epoch_key: str | None = None
        for epoch in plan.epochs:
            t_epoch = time.perf_counter()
            started = datetime.now(UTC).isoformat(timespec="seconds")
            reporter.epoch_started(epoch, epoch.index, len(plan.epochs))
            info = EpochInfo(id=epoch.id, index=epoch.index, role=epoch.role, seed=plan.seed,
                             workflow_dir=plan.base_dir, units=plan.units)
            input_digests = [digests[(epoch.index, i)] for i in range(len(epoch.inputs))]
            recent = [_read_input(plan, registry, epoch, i, input_digests[i]) for i in range(len(epoch.inputs))]
            slots: dict[str, Any] = {"recent": recent, "epoch": info}
            if composite is not None:
                slots["reference"] = composite
            upstream = [upstream_epoch_key] if upstream_epoch_key else []
            stage_records = []
            for stage in epoch.stages:
                spec, s_index = stage.spec, stage.index
                params = json.loads(stage.params.model_dump_json())
                rng, seed = _stage_rng(plan.seed, epoch.index, s_index)
                key = cache_key(spec, params, input_digests, upstream)
                where = f"epoch {epoch.id}, stage {s_index} {spec.name!r} ({spec.plugin} {spec.plugin_version})"
                visible = {k: v for k, v in slots.items() if k in spec.requires or k in spec.optional or k == "epoch"}
                ctx = StageContext(stage=spec, params=stage.params, slots=visible, epoch=info, rng=rng, seed=seed,
                                   log=logging.getLogger(f"gdt.stage.{spec.name}"), progress=reporter.progress)
                reporter.stage_started(epoch, s_index, spec)
                t0 = time.perf_counter()
                slots.update(_run_stage(spec, ctx, where))
                dt = time.perf_counter() - t0
                reporter.stage_finished(epoch, s_index, spec, dt)
                log.info("stage done", extra={"event": {"epoch": epoch.id, "stage": spec.name, "index": s_index,
                                                        "seconds": round(dt, 4), "cache_key": key}})
                upstream.append(key)
                stage_records.append({"index": s_index, "id": stage.id, "uses": spec.name, "family": spec.family,
                                      "version": spec.version, "plugin": spec.plugin,
                                      "plugin_version": spec.plugin_version, "entry_point": spec.entry_point,
                                      "params": params, "seed_spawn_key": [epoch.index, s_index], "seed": seed,
                                      "requires": list(spec.requires), "provides": list(spec.provides),
                                      "cache_key": key, "seconds": round(dt, 4),
                                      "report": json.loads(json.dumps(ctx.notes, default=_plain))})
            composite = slots["composite"]
            upstream_epoch_key = upstream[-1] if upstream else None
            inputs = [{"path": ds.source.path, "sha256": ds.source.sha256, "name": ds.name, "kind": ds.kind,
                       "kind_hint": inp.kind, "reader": ds.source.reader, "units": ds.source.units,
                       "scale": ds.source.scale, "viewpoints": inp.viewpoints, "elements": ds.n_elements}
                      for ds, inp in zip(recent, epoch.inputs, strict=True) if ds.source is not None]
            provenance = {
                "gdt_pipeline": packages.get("gdt-pipeline", "?"),
                "workflow": workflow_record,
                "epoch": {"id": epoch.id, "index": epoch.index, "role": epoch.role},
                "seed": plan.seed, "inputs": inputs, "stages": stage_records,
                "registration": _registration_record(slots.get("registration")),
                "packages": packages, "python": platform.python_version(),
                "started": started, "finished": datetime.now(UTC).isoformat(timespec="seconds"),
                "counts": composite.counts(), "epoch_key": upstream_epoch_key,
            }
            rov = slots.get("rov")
            segments = [dataclasses.asdict(g) for g in composite.segments]
            layer = store.write_epoch(epoch.id, composite_to_elements(composite), provenance,
                                      None if rov is None else (rov.vertices, rov.faces), segments)
            summary = EpochSummary(epoch.id, composite.counts(), time.perf_counter() - t_epoch,
                                   target / "epochs" / Path(layer).name)
            result.epochs.append(summary)
            reporter.epoch_finished(summary)
            lock["epochs"].append({"id": epoch.id, "inputs": inputs, "epoch_key": upstream_epoch_key,
                                   "stages": [{k: r[k] for k in ("uses", "plugin", "plugin_version", "version",
                                                                 "params", "seed", "cache_key")}
                                              for r in stage_records]})
        _write_json_atomic(staging / LOCK_NAME, lock)
        _swap_into_place(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return result


def _plain(value: Any) -> Any:
    """JSON form of numpy scalars and arrays in stage reports."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def _registration_record(reg: Registration | None) -> dict[str, Any] | None:
    if reg is None:
        return None
    return {"method": reg.method, "transform": reg.transform.tolist(), "fitness": reg.fitness, "rmse": reg.rmse,
            "covariance": None if reg.covariance is None else reg.covariance.tolist(),
            "covariance_center": reg.center.tolist()}


def _write_json_atomic(path: Path, data: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2, sort_keys=True, default=str)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _swap_into_place(staging: Path, target: Path) -> None:
    """Move the finished twin into place; an old twin is moved aside first and removed only after the move."""
    old = None
    if target.exists():
        old = target.parent / f".{target.name}.old-{os.getpid()}"
        os.replace(target, old)
    try:
        os.replace(staging, target)
    except BaseException:
        if old is not None:
            os.replace(old, target)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)

