"""The records a run writes: ``gdt.lock``, the run record in the twin folder (the seed, the packages, every epoch's
inputs and cache keys and the layer sha256s; a run on an existing twin keeps the records of the epochs it keeps as
they were and appends its own, and ``runs`` lists which run made which epochs), and the input and registration
records of an epoch's provenance."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from twin_store import RUN_LOCK_NAME, TwinStore

from ..provenance import EpochProvenance, InputRecord, WorkflowRecord
from ..types import Dataset, Registration
from .plan import InputPlan


def _old_entries(twin: Path) -> tuple[dict[str, dict[str, Any]], list[dict[str, Any]]]:
    """The epoch records and the runs of the twin's gdt.lock, by epoch id; nothing when it is missing or unreadable
    (the layers' provenance holds the same records)."""
    try:
        data = json.loads((twin / RUN_LOCK_NAME).read_text(encoding="utf-8"))
        entries = {str(e["id"]): e for e in data["epochs"] if isinstance(e, dict) and "id" in e}
        runs = [r for r in data.get("runs", []) if isinstance(r, dict)]
    except (OSError, ValueError, KeyError, TypeError):
        return {}, []
    return entries, runs


def start_record(workflow: WorkflowRecord, seed: int, packages: dict[str, str], twin: Path | None,
                 store: TwinStore | None, kept: list[str]) -> dict[str, Any]:
    """The run record a run begins with: the kept epochs' records from the twin's lock (or, where it lacks one,
    from the epoch's layer), and a new entry under ``runs``."""
    entries, runs = _old_entries(twin) if twin is not None and kept else ({}, [])
    epochs = []
    for eid in kept:
        assert store is not None
        epochs.append(entries.get(eid) or EpochProvenance.from_dict(store.provenance(eid)).lock_entry())
    kept_set = set(kept)
    runs = [{**r, "epochs": [e for e in r.get("epochs", []) if e in kept_set]} for r in runs]
    runs = [r for r in runs if r["epochs"]]
    if kept and not runs:  # a lock written before runs were listed: the kept epochs came from one earlier run
        runs = [{"epochs": list(kept)}]
    runs.append({"workflow": dataclasses.asdict(workflow), "packages": packages, "epochs": []})
    return {"format": 1, "workflow": dataclasses.asdict(workflow), "seed": seed, "packages": packages,
            "epochs": epochs, "runs": runs}


def add_epoch(record: dict[str, Any], prov: EpochProvenance) -> None:
    """Append an epoch this run made."""
    record["epochs"].append(prov.lock_entry())
    record["runs"][-1]["epochs"].append(prov.epoch.id)


def input_record(parts: list[Dataset], poses: list[dict[str, Any]], inp: InputPlan) -> InputRecord:
    """The provenance of one input: the file, the reader, and per dataset it gave its name, size, identity and the
    station it was given (with where that came from)."""
    src = parts[0].source
    assert src is not None
    datasets = [{"name": ds.name, "kind": ds.kind, "elements": ds.n_elements, **({"meta": ds.meta} if ds.meta else {}),
                 **pose} for ds, pose in zip(parts, poses, strict=True)]
    kinds = {ds.kind for ds in parts}
    return InputRecord(path=src.path, sha256=src.sha256, name=inp.name, kind=kinds.pop() if len(kinds) == 1
                       else "mixed", kind_hint=inp.kind, reader=src.reader, units=src.units, scale=src.scale,
                       viewpoints=inp.viewpoints, elements=sum(ds.n_elements for ds in parts), notes=dict(src.notes),
                       datasets=datasets, params=inp.params)


def plain(value: Any) -> Any:
    """JSON form of numpy scalars and arrays in stage reports."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def registration_record(reg: Registration | None) -> dict[str, Any] | None:
    """The registration as its provenance records it (None when the epoch had none)."""
    if reg is None:
        return None
    return {"method": reg.method, "transform": reg.transform.tolist(), "fitness": reg.fitness, "rmse": reg.rmse,
            "covariance": None if reg.covariance is None else reg.covariance.tolist(),
            "covariance_center": reg.center.tolist()}
