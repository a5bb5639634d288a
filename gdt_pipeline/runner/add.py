"""``gdt add``: one new as-is epoch for a twin, run with the stage chain the twin recorded for an earlier epoch (by
default its last as-is one), so that a new scan needs no workflow editing. The epoch's inputs are read like any
other (reader by extension, the station from the file's header or a pose file beside it), and the workflow it ran
is written into its provenance."""

from __future__ import annotations

import hashlib
import json
import os
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import yaml

from twin_store import TwinStore

from ..errors import GdtError
from ..names import identifier
from ..plugins import Registry
from ..provenance import EpochProvenance, InputRecord
from .plan import EpochPlan, InputPlan, RunPlan
from .recorded import recorded_stage

_NUMBERED = re.compile(r"(.*?)(\d+)")


def next_epoch_id(held: list[str]) -> str | None:
    """The id after the twin's last one when its ids count up (E0, E1 -> E2), else None."""
    found = [_NUMBERED.fullmatch(e) for e in held]
    if not found or any(m is None for m in found) or len({m.group(1) for m in found if m}) != 1:
        return None
    prefix = found[0].group(1) if found[0] else ""
    return f"{prefix}{max(int(m.group(2)) for m in found if m) + 1}"


def template_epoch(store: TwinStore, like: str | None) -> EpochProvenance:
    """The recorded epoch whose chain the new one runs: ``like``, else the twin's last as-is epoch."""
    held = store.epochs()
    if like is not None:
        if like not in held:
            raise GdtError(f"--like {like}: twin {store.path} has no such epoch ({', '.join(held)})")
        return EpochProvenance.from_dict(store.provenance(like))
    for eid in reversed(held):
        prov = EpochProvenance.from_dict(store.provenance(eid))
        if prov.epoch.role == "as-is":
            return prov
    raise GdtError(f"twin {store.path} has no as-is epoch whose stage chain a new scan could run with (epochs: "
                   f"{', '.join(held)}); run a workflow with a first scan, or name one with --like")


def _input(path: Path, registry: Registry, template: list[InputRecord], name: str, reader: str | None,
           units: str | None, default_units: str, viewpoint: tuple[float, float, float] | None) -> InputPlan:
    """A new input, with the reader parameters of the template's input read by the same reader (LAS classes)."""
    if not path.is_file():
        raise GdtError(f"gdt add: {path} is not a file")
    chosen = reader or next((r.name for r in registry.readers_for(path, None)), None)
    if chosen is None:
        exts = sorted({x for s in registry.stages("reader") for x in s.extensions})
        raise GdtError(f"gdt add: no installed reader accepts {path.name!r} (extensions: {', '.join(exts)})")
    params = next((r.params for r in template if r.reader == chosen and r.params), None)
    return InputPlan(path=path, name=name, reader=reader, units=units or default_units, params=params,
                     units_given=units is not None, viewpoints=None if viewpoint is None else [list(viewpoint)])


def _workflow_text(store: TwinStore, prov: EpochProvenance, epoch: EpochPlan, base: Path) -> str:
    """The workflow file of the new epoch alone, as ``gdt run`` would read it (recorded in its provenance)."""
    wf = prov.workflow
    data: dict[str, Any] = {
        "name": wf.name, "twin": os.path.relpath(store.path.resolve(), base), "seed": int(prov.seed),
        "units": wf.units, "up_axis": wf.up_axis,
        "epochs": [{"id": epoch.id, "role": epoch.role, "inputs": [
            {"path": os.path.relpath(inp.path, base), "name": inp.name,
             **({"reader": inp.reader} if inp.reader else {}), **({"units": inp.units} if inp.units_given else {}),
             **({"viewpoints": inp.viewpoints} if inp.viewpoints else {}),
             **({"with": inp.params} if inp.params else {})} for inp in epoch.inputs]}],
        "stages": [{"uses": st.spec.name, **({"id": st.id} if st.id else {}),
                    "with": json.loads(st.params.model_dump_json())} for st in epoch.stages]}
    head = (f"# written by `gdt add` at {datetime.now(UTC).isoformat(timespec='seconds')}: epoch {epoch.id} run with "
            f"the stage chain of epoch {prov.epoch.id} (stage indices in the twin: "
            f"{', '.join(str(st.index) for st in epoch.stages)})\n")
    return head + yaml.safe_dump(data, sort_keys=False)


def plan_for_scans(store: TwinStore, registry: Registry, files: list[Path], *, epoch_id: str | None = None,
                   like: str | None = None, name: str | None = None, reader: str | None = None,
                   units: str | None = None, viewpoint: tuple[float, float, float] | None = None
                   ) -> tuple[RunPlan, list[str]]:
    """The plan of one new as-is epoch reading ``files``, with a recorded epoch's chain; version warnings."""
    held = store.epochs()
    new_id = epoch_id or next_epoch_id(held)
    if new_id is None:
        raise GdtError(f"twin {store.path}: its epoch ids ({', '.join(held)}) do not count up; name the new one "
                       f"with --id")
    if new_id in held or identifier(new_id) != new_id:
        raise GdtError(f"--id {new_id}: " + ("the twin already holds it" if new_id in held else
                                              "an epoch id is letters, digits and _, not starting with a digit"))
    if (name is not None or viewpoint is not None) and len(files) > 1:
        raise GdtError("--name and --viewpoint describe one input; give one file (or pose files beside several)")
    prov = template_epoch(store, like)
    warnings: list[str] = []
    stages = [recorded_stage(prov.epoch.id, rec, registry, warnings) for rec in prov.stages]
    paths = [Path(f).resolve() for f in files]
    inputs = [_input(p, registry, prov.inputs, name or identifier(p.stem), reader, units, prov.workflow.units,
                     viewpoint) for p in paths]
    base = Path(os.path.commonpath([p.parent for p in paths]))
    epoch = EpochPlan(id=new_id, index=len(held), role="as-is", inputs=inputs, stages=stages)
    text = _workflow_text(store, prov, epoch, base)
    plan = RunPlan(name=prov.workflow.name, workflow_path=base / f"{new_id}.gdt-add.yaml",
                   workflow_sha256=hashlib.sha256(text.encode()).hexdigest(), base_dir=base, seed=int(prov.seed),
                   units=prov.workflow.units, up_axis=prov.workflow.up_axis, epochs=[epoch], workflow_text=text)
    return plan, warnings
