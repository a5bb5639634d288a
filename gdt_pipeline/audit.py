"""Reproducible epoch audits: re-run a twin's epochs from their recorded provenance and prove they match.

For each epoch audited (all of them, or one: ``--epoch``), the provenance in its layer names the inputs (path
relative to the workflow folder, sha256, reader, units), the seed, and every stage with its plugin, versions and
resolved parameters. The audit checks every input still has its recorded sha256, rebuilds the run plan from the
record alone (the workflow file is not needed and may have changed since), re-runs it into a scratch twin, and
compares every element set of every epoch with the stored layers: geometry, uncertainty, scores, states, visibility,
source epochs. One epoch is re-run from the twin's own composite before it (the scratch twin starts as the stored
layers up to there), so only its own inputs are needed.

What is bit-exact: everything, on the same package versions and CPU architecture (the built-in stages use no
thread-count-dependent reductions: cKDTree queries, Open3D closest-point and ray queries, batched 3x3 linear
algebra). Across machines or library versions, floating-point results may differ in the last bits, so floats are
compared with a stated tolerance (``rtol``/``atol``) and the report says whether the match was exact. A twin built
in tiles is re-run in the same tiles (their sizes are in the stages' reports), in this process.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import tempfile
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from twin_store import ElementSet, TwinStore

from .errors import GdtError
from .plugins import Registry, load_registry
from .provenance import EpochProvenance
from .runner import EpochPlan, RunPlan, TilingOptions, execute_plan
from .runner.recorded import inputs_dir, recorded_inputs, recorded_stage

EXACT_FIELDS = ("faces", "ids", "state", "visible", "source_epoch")
FLOAT_FIELDS = ("points", "covariance", "half_widths", "rotation", "uncertainty_summary", "score", "p_value")


@dataclass
class Difference:
    """Elements of one field of one element set that differ between the stored twin and the re-run."""

    key: str
    field: str
    count: int
    first: list[int] = field(default_factory=list)
    stored: list[Any] = field(default_factory=list)
    rerun: list[Any] = field(default_factory=list)

    def text(self) -> str:
        """One line for people."""
        if not self.first:
            return f"{self.key}.{self.field}: {self.stored} stored, {self.rerun} re-run"
        pairs = ", ".join(f"[{i}] {s} != {r}" for i, s, r in zip(self.first[:3], self.stored, self.rerun,
                                                                 strict=False))
        return f"{self.key}.{self.field}: {self.count} element(s) differ, first {pairs}"


@dataclass
class EpochAudit:
    """The verdict on one epoch."""

    epoch: str
    verdict: str  # match, differs, inputs changed, not re-run
    exact: bool = False
    cache_keys_match: bool | None = None
    input_problems: list[str] = field(default_factory=list)
    differences: list[Difference] = field(default_factory=list)


@dataclass
class AuditReport:
    """The audit of a twin: a verdict per epoch, version warnings and errors."""

    twin: str
    epochs: list[EpochAudit] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    strict: bool = False

    @property
    def ok(self) -> bool:
        """True only when every audited epoch matches (and, with strict, nothing warned)."""
        return (not self.errors and bool(self.epochs) and all(e.verdict == "match" for e in self.epochs)
                and not (self.strict and self.warnings))

    def to_dict(self) -> dict[str, Any]:
        """Machine-readable report."""
        return {"twin": self.twin, "ok": self.ok, "strict": self.strict, "warnings": self.warnings,
                "errors": self.errors, "epochs": [asdict(e) for e in self.epochs]}


def _per_element(mask: np.ndarray) -> np.ndarray:
    return mask.reshape(mask.shape[0], -1).any(axis=1) if mask.ndim > 1 else mask


def _short(v: Any) -> Any:
    arr = np.asarray(v)
    return arr.round(9).tolist() if arr.dtype.kind == "f" else arr.tolist()


def compare_element_sets(stored: list[ElementSet], rerun: list[ElementSet], *, rtol: float, atol: float
                         ) -> tuple[list[Difference], bool]:
    """Differences between two composites, per set and field; and whether they are bit-identical."""
    diffs: list[Difference] = []
    exact = True
    a_by, b_by = {e.key: e for e in stored}, {e.key: e for e in rerun}
    for key in sorted(set(a_by) ^ set(b_by)):
        diffs.append(Difference(key, "presence", 1, stored=[key in a_by], rerun=[key in b_by]))
    for key in sorted(set(a_by) & set(b_by)):
        a, b = a_by[key], b_by[key]
        if a.kind != b.kind or a.uncertainty_model != b.uncertainty_model:
            diffs.append(Difference(key, "kind/uncertainty model", 1, stored=[a.kind, a.uncertainty_model],
                                    rerun=[b.kind, b.uncertainty_model]))
            continue
        for name in EXACT_FIELDS + FLOAT_FIELDS:
            va, vb = getattr(a, name), getattr(b, name)
            if va is None and vb is None:
                continue
            if va is None or vb is None or np.shape(va) != np.shape(vb):
                diffs.append(Difference(key, name, 1, stored=[None if va is None else list(np.shape(va))],
                                        rerun=[None if vb is None else list(np.shape(vb))]))
                continue
            va, vb = np.asarray(va), np.asarray(vb)
            if name in EXACT_FIELDS:
                bad = _per_element(va != vb)
            else:
                same_bits = np.array_equal(va, vb, equal_nan=True)
                exact &= same_bits
                bad = np.zeros(len(va), bool) if same_bits else _per_element(
                    ~np.isclose(va, vb, rtol=rtol, atol=atol, equal_nan=True))
            if bad.any():
                idx = np.flatnonzero(bad)
                diffs.append(Difference(key, name, int(idx.size), first=idx[:10].tolist(),
                                        stored=[_short(va[i]) for i in idx[:3]],
                                        rerun=[_short(vb[i]) for i in idx[:3]]))
    return diffs, exact and not diffs


def plan_from_twin(store: TwinStore, registry: Registry, epochs: list[str], *, base_dir: Path | None = None
                   ) -> tuple[RunPlan, list[str], dict[str, list[str]]]:
    """The run plan a twin's provenance records for ``epochs``; version warnings; input problems per epoch."""
    warnings: list[str] = []
    problems: dict[str, list[str]] = {}
    plans: list[EpochPlan] = []
    records = [EpochProvenance.from_dict(store.provenance(eid)) for eid in epochs]
    for eid, prov in zip(epochs, records, strict=True):
        found: list[str] = []
        inputs = recorded_inputs(prov, inputs_dir(store, prov, base_dir), found)
        if found:
            problems[eid] = found
        stages = [recorded_stage(eid, rec, registry, warnings) for rec in prov.stages]
        plans.append(EpochPlan(id=eid, index=prov.epoch.index, role=prov.epoch.role, inputs=inputs, stages=stages))
    wf = records[0].workflow
    base = inputs_dir(store, records[0], base_dir)
    plan = RunPlan(name=wf.name, workflow_path=base / wf.path, workflow_sha256=wf.sha256, base_dir=base,
                   seed=int(records[0].seed), units=wf.units, up_axis=wf.up_axis, epochs=plans)
    return plan, warnings, problems


def recorded_tiling(store: TwinStore, epochs: list[str]) -> TilingOptions | None:
    """The tiles a run used, from its stages' reports: replayed in this process, so that stages drawing random
    numbers per tile draw what they drew (the twin is the same on every executor)."""
    sizes = []
    for eid in epochs:
        for rec in store.provenance(eid).get("stages", []):
            tiling = rec.get("report", {}).get("tiling") if isinstance(rec.get("report"), dict) else None
            if tiling:
                sizes.append((eid, float(tiling["tile_size"])))
                break
    if not sizes:
        return None
    return TilingOptions(executor="serial", tile=sizes[0][1], epoch_sizes=tuple(sizes))


def audit_twin(twin: str | Path, *, epoch: str | None = None, strict: bool = False, base_dir: Path | None = None,
               rtol: float = 1e-6, atol: float = 1e-9, registry: Registry | None = None) -> AuditReport:
    """Re-run a twin's epochs from their provenance and compare with what is stored: all of them, or only ``epoch``
    (from the twin's composite before it, with that epoch's own inputs alone)."""
    registry = registry or load_registry()
    store = TwinStore.open(twin)
    epochs = store.epochs()
    if not epochs:
        raise GdtError(f"twin {twin} has no epochs to audit")
    if epoch is not None and epoch not in epochs:
        raise GdtError(f"twin {twin} has no epoch {epoch!r} (epochs: {', '.join(epochs)})")
    store.verify()  # a layer that is not the file that was written is an error before anything is re-run
    report = AuditReport(twin=str(Path(twin).resolve()), strict=strict)
    audited = epochs if epoch is None else [epoch]
    plan, report.warnings, problems = plan_from_twin(store, registry, audited, base_dir=base_dir)
    lock_problems = store.run_lock_problems()
    report.warnings += lock_problems
    if strict and lock_problems:  # the run record is what a strict audit checks first: no re-run can pass it
        report.epochs += [EpochAudit(e, "not re-run", input_problems=["strict: the run record gdt.lock has "
                                                                       "problems (see the warnings)"])
                          for e in audited]
        return report
    broken = next((i for i, e in enumerate(audited) if e in problems), None)
    runnable = audited if broken is None else audited[:broken]
    with _scratch(store) as scratch:
        rerun_store = _rerun(store, registry, plan, runnable, epochs.index(audited[0]), scratch)
        for i, eid in enumerate(audited):
            if eid in problems:
                report.epochs.append(EpochAudit(eid, "inputs changed", input_problems=problems[eid]))
                continue
            if broken is not None and i > broken:
                report.epochs.append(EpochAudit(eid, "not re-run", input_problems=[
                    f"builds on epoch {audited[broken]}, whose inputs changed"]))
                continue
            assert rerun_store is not None
            report.epochs.append(_compared(store, rerun_store, eid, rtol, atol))
    return report


@contextlib.contextmanager
def _scratch(store: TwinStore) -> Iterator[Path]:
    """A scratch folder for the re-run: beside the twin where that is writable (the kept layers are then hard
    links, whatever their size), else in the system's temp folder (they are copied)."""
    parent = store.path.resolve().parent
    where = parent if os.access(parent, os.W_OK) else None
    with tempfile.TemporaryDirectory(prefix=f".{store.path.name}.audit-", dir=where) as scratch:
        yield Path(scratch)


def _rerun(store: TwinStore, registry: Registry, plan: RunPlan, runnable: list[str], first: int, scratch: Path
           ) -> TwinStore | None:
    """Re-run the ``runnable`` epochs into a scratch twin that starts as the stored twin's first ``first`` epochs."""
    if not runnable:
        return None
    target = scratch / "twin"
    sub = dataclasses.replace(plan, epochs=plan.epochs[: len(runnable)])
    if first:
        store.branch(target, store.epochs()[:first])
    rerun = execute_plan(sub, registry, target, append=bool(first), tiling=recorded_tiling(store, runnable))
    return TwinStore.open(rerun.twin)


def _compared(store: TwinStore, rerun_store: TwinStore, eid: str, rtol: float, atol: float) -> EpochAudit:
    """The verdict on one re-run epoch: its element sets and cache keys against the stored ones."""
    diffs, exact = compare_element_sets(store.read_epoch(eid), rerun_store.read_epoch(eid), rtol=rtol, atol=atol)
    keys_a = [s.cache_key for s in EpochProvenance.from_dict(store.provenance(eid)).stages]
    keys_b = [s.cache_key for s in EpochProvenance.from_dict(rerun_store.provenance(eid)).stages]
    return EpochAudit(eid, "match" if not diffs else "differs", exact=exact, cache_keys_match=keys_a == keys_b,
                      differences=diffs)
