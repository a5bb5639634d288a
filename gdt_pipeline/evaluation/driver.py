"""``gdt eval``'s driver: run (or read) a workflow's twin and score every as-is epoch that has ground truth."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from twin_store import TwinStore

from ..plugins import Registry, load_registry
from ..runner import run_workflow
from ..workflow import load_workflow
from .epoch import evaluate_epoch
from .peer_runs import C2C_TAU, PEERS


def evaluate(workflow: str | Path, *, twin: str | Path | None = None, registry: Registry | None = None,
             peers: tuple[str, ...] = PEERS, seed: int = 0, progress: Any = None) -> tuple[dict[str, Any], dict]:
    """Run (or read) the twin of a workflow and score every as-is epoch that has ground truth, with the peers.

    Returns the result (JSON-ready) and the per-point arrays the report plots.
    """
    say = progress or (lambda msg: None)
    registry = registry or load_registry()
    wf = load_workflow(workflow, registry)
    started = time.perf_counter()
    if twin is None:
        say(f"running {wf.path.name} ...")
        twin_path = run_workflow(workflow, registry=registry, overwrite=True).twin
    else:
        twin_path = Path(twin)
    store = TwinStore.open(twin_path)
    rng = np.random.default_rng(seed)
    result: dict[str, Any] = {"workflow": str(wf.path), "twin": str(twin_path), "scene": None, "seed": seed,
                              "c2c_tau": C2C_TAU, "epochs": []}
    arrays: dict[str, Any] = {}
    epochs = wf.model.epochs
    for index, epoch in enumerate(epochs):
        if epoch.role != "as-is" or index == 0:
            continue
        say(f"scoring {epoch.id} ...")
        row, arr = evaluate_epoch(wf, store, epochs[index - 1].id, epoch, registry, peers, rng, say)
        if row.get("scene"):
            result["scene"] = row.pop("scene")
        result["epochs"].append(row)
        if arr:
            arrays[epoch.id] = arr
    result["seconds"] = round(time.perf_counter() - started, 2)
    return result, arrays
