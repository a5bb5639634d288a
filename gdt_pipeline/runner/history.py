"""A run on an existing twin: which of the workflow's epochs the twin already holds, compared record by record, and
where the run starts. An epoch the twin holds is never re-run: the next one starts from the composite the twin
stores. A workflow that describes a held epoch otherwise (an input, a stage, a parameter, a stage version, the seed)
is an error naming the epoch and the difference, unless the run rebuilds from before it (``--from``)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from twin_store import TwinStore

from ..errors import GdtError
from ..provenance import EpochProvenance, InputRecord, StageRecord
from .inputs import relative_to_workflow, sha256_file
from .plan import EpochPlan, InputPlan, RunPlan, StagePlan


class HistoryError(GdtError):
    """The workflow describes an epoch the twin holds differently, or names an epoch it does not have."""


@dataclass(frozen=True)
class Start:
    """Where a run on an existing twin begins: the twin's epochs it keeps (oldest first) and those it replaces."""

    kept: list[str]
    replaced: list[str] = field(default_factory=list)
    extra: list[str] = field(default_factory=list)  # epochs the twin holds beyond the workflow's (kept as they are)
    notes: list[str] = field(default_factory=list)  # what was taken on trust: held inputs whose files are gone


def _input_differences(inp: InputPlan, rec: InputRecord, base: Path, notes: list[str], where: str) -> list[str]:
    """How a workflow input differs from the recorded one (its file hashed when it is still there)."""
    out = []
    path = relative_to_workflow(inp.path, base)
    if path != rec.path:
        out.append(f"{where}: the workflow reads {path}, the twin recorded {rec.path}")
    elif not inp.path.is_file():
        notes.append(f"{where}: {path} is gone; its recorded sha256 {rec.sha256[:12]} stands")
    elif (digest := sha256_file(inp.path)) != rec.sha256:
        out.append(f"{where}: {path} has sha256 {digest[:12]}, the twin was made from {rec.sha256[:12]}")
    for name, mine, theirs in (("reader", inp.reader, rec.reader if inp.reader else None),
                               ("kind", inp.kind, rec.kind_hint),
                               ("units", inp.units if inp.units_given else None,
                                rec.units if inp.units_given else None),
                               ("viewpoints", inp.viewpoints, rec.viewpoints), ("name", inp.name, rec.name),
                               ("with", inp.params or None, rec.params or None)):
        if _plain(mine) != _plain(theirs):
            out.append(f"{where}: {name} is {_shown(mine)} in the workflow, {_shown(theirs)} in the twin")
    return out


def _stage_differences(st: StagePlan, rec: StageRecord, where: str) -> list[str]:
    """How a workflow stage differs from the recorded one: what it uses, its version, its parameters."""
    spec = st.spec
    if spec.name != rec.uses:
        return [f"{where}: the workflow uses {spec.name!r}, the twin recorded {rec.uses!r}"]
    out = []
    if spec.version != rec.version:
        out.append(f"{where} {spec.name!r}: stage version {spec.version} is installed, the twin was made with "
                   f"{rec.version} ({rec.plugin} {rec.plugin_version})")
    params = json.loads(st.params.model_dump_json())
    for key in sorted(set(params) | set(rec.params)):
        if _plain(params.get(key)) != _plain(rec.params.get(key)):
            out.append(f"{where} {spec.name!r}: parameter {key} is {_shown(params.get(key))} in the workflow, "
                       f"{_shown(rec.params.get(key))} in the twin")
    return out


def epoch_differences(plan: RunPlan, epoch: EpochPlan, rec: EpochProvenance, notes: list[str]) -> list[str]:
    """Everything that differs between a workflow epoch and the epoch the twin recorded at its place."""
    if epoch.id != rec.epoch.id:
        return [f"the twin holds epoch {rec.epoch.id} where the workflow has {epoch.id}"]
    out = []
    if epoch.role != rec.epoch.role:
        out.append(f"role is {epoch.role} in the workflow, {rec.epoch.role} in the twin")
    if plan.seed != rec.seed:
        out.append(f"seed is {plan.seed} in the workflow, {rec.seed} in the twin")
    if plan.units != rec.workflow.units:
        out.append(f"twin units are {plan.units} in the workflow, {rec.workflow.units} in the twin")
    if len(epoch.inputs) != len(rec.inputs):
        out.append(f"{len(epoch.inputs)} inputs in the workflow, {len(rec.inputs)} in the twin")
    for i, (inp, irec) in enumerate(zip(epoch.inputs, rec.inputs, strict=False)):
        out += _input_differences(inp, irec, plan.base_dir, notes, f"input {i}")
    if len(epoch.stages) != len(rec.stages):
        out.append(f"{len(epoch.stages)} stages in the workflow ({', '.join(s.spec.name for s in epoch.stages)}), "
                   f"{len(rec.stages)} in the twin ({', '.join(s.uses for s in rec.stages)})")
    for st, srec in zip(epoch.stages, rec.stages, strict=False):
        out += _stage_differences(st, srec, f"stage {st.index}")
    return out


def start_on(plan: RunPlan, store: TwinStore, from_epoch: str | None = None) -> Start:
    """Which of the twin's epochs a run of ``plan`` keeps; a HistoryError when a held epoch differs (unless the run
    rebuilds from ``from_epoch`` or before) or ``from_epoch`` is an epoch neither knows."""
    held = store.epochs()
    planned = [e.id for e in plan.epochs]
    if from_epoch is not None and from_epoch not in held and from_epoch not in planned:
        raise HistoryError(f"--from {from_epoch}: no such epoch in the twin {store.path} ({', '.join(held)}) or the "
                           f"workflow ({', '.join(planned)})")
    limit = held.index(from_epoch) if from_epoch in held else len(held)
    notes: list[str] = []
    for i, eid in enumerate(held[:limit]):
        if i >= len(plan.epochs):
            return Start(kept=held[:limit], extra=held[i:limit], notes=notes)
        rec = EpochProvenance.from_dict(store.provenance(eid))
        found = epoch_differences(plan, plan.epochs[i], rec, notes)
        if found:
            raise HistoryError(f"epoch {eid}: the workflow differs from what the twin {store.path} holds: "
                               + "; ".join(found) + f". The twin keeps its epochs as they were made: rebuild from "
                               f"this epoch with --from {eid}, or everything with --overwrite")
    return Start(kept=held[:limit], replaced=held[limit:], notes=notes)


def _plain(value: Any) -> Any:
    """A value as JSON would carry it (tuples as lists), so a workflow's value compares with a recorded one."""
    return json.loads(json.dumps(value, default=str))


def _shown(value: Any) -> str:
    return "unset" if value is None else json.dumps(value, default=str)
