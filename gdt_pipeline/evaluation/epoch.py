"""One as-is epoch scored against its ground truth: the workflow's change mask and the peers' on the same points,
then removed geometry, new objects, the twin's segments and the composite's distance to the true surfaces."""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from twin_store import TwinStore

from ..geometry import ReferenceIndex
from ..plugins import Registry
from ..provenance import EpochProvenance
from .metrics import prf
from .peer_runs import c2c_methods, m3c2_peers
from .scoring import composite_distance, score_new_objects, score_removal, score_segments
from .truth import read_epoch_truth, read_scan_truth
from .twin_points import composite_from_twin


def gdt_seconds(store: TwinStore, epoch: str) -> float | None:
    """The workflow's own time for an epoch (the sum of its stages), from the twin's provenance."""
    try:
        stages = EpochProvenance.from_dict(store.provenance(epoch)).stages
    except Exception:  # an older twin without the record: the time is simply not known
        return None
    return round(sum(s.seconds for s in stages), 3) if stages else None


def evaluate_epoch(wf: Any, store: TwinStore, prev_id: str, epoch: Any, registry: Registry,
                   peers: tuple[str, ...], rng: np.random.Generator, say: Any) -> tuple[dict[str, Any], dict]:
    """The epoch's result row and the per-point arrays the report plots ({} when no scan has truth)."""
    sets = {es.key: es for es in store.read_epoch(epoch.id)}
    prev_sets = store.read_epoch(prev_id)
    truth, pred, missing, scene_dir = read_scan_truth(wf, epoch, sets, registry)
    row: dict[str, Any] = {"epoch": epoch.id, "missing_truth": missing, "methods": [], "notes": []}
    if not pred:
        return row, {}
    t_changed, points = truth.cat("changed").astype(bool), np.vstack(truth.points)
    epoch_truth = read_epoch_truth(scene_dir, epoch.id)
    if epoch_truth is not None and (scene_dir / "scene.json").is_file():
        row["scene"] = json.loads((scene_dir / "scene.json").read_text()).get("scene", scene_dir.name)
    row.update(points=len(t_changed), changed=int(t_changed.sum()))
    methods: dict[str, dict[str, Any]] = {}
    methods["gdt"] = {"label": "gdt (this workflow)", "kind": "ours", "changed": np.concatenate(pred),
                      "distance": None, "index": None, "seconds": gdt_seconds(store, epoch.id), "params": {}}
    reference = ReferenceIndex(composite_from_twin(store, prev_id))
    if "c2c" in peers:
        methods.update(c2c_methods(reference, points, t_changed))
    if "m3c2" in peers or "m3c2ep" in peers:
        m3c2_peers(methods, peers, prev_sets, points, t_changed, truth, rng, row, say)
    row["methods"] += score_methods(methods, t_changed)
    if epoch_truth is not None:
        row["removal"] = score_removal(epoch_truth, prev_sets, sets, points, reference)
        row["objects"] = score_new_objects(epoch_truth, methods, points, truth)
        row["segments"] = score_segments(store.read_segments(epoch.id), epoch_truth, truth, prev_sets,
                                         row["objects"])
        row["composite"] = composite_distance(scene_dir, epoch_truth, list(sets.values()), rng)
    else:
        row["removal"], row["objects"], row["composite"] = None, [], None
        row["notes"].append(f"no truth_{epoch.id}.npz in the scene directory: removal, objects and composite skipped")
    arr = {"points": points, "truth": t_changed,
           "methods": {n: {"changed": m["changed"], "distance": m["distance"], "index": m["index"]}
                       for n, m in methods.items()}}
    return row, arr


def score_methods(methods: dict[str, dict[str, Any]], t_changed: np.ndarray) -> list[dict[str, Any]]:
    """One result row per method: its change mask scored on the truth (a subsample on its own points)."""
    rows = []
    for name, m in methods.items():
        idx = m["index"]
        scores = prf(m["changed"], t_changed if idx is None else t_changed[idx])
        rows.append({"name": name, "label": m["label"], "kind": m["kind"], **scores,
                     "seconds": m["seconds"], "params": m["params"]})
    return rows
