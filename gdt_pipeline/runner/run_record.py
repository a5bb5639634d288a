"""``gdt.lock``, the run record in the twin folder: the seed, the packages, every epoch's inputs and cache keys and the
layer sha256s. A run on an existing twin keeps the records of the epochs it keeps as they were and appends its own;
``runs`` lists which run made which epochs."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from twin_store import RUN_LOCK_NAME, TwinStore

from ..provenance import EpochProvenance, WorkflowRecord


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
