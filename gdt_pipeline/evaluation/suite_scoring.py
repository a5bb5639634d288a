"""One suite scene's twin scored against its truth: change F1 (per point; per facet weighted by area for mesh
scans) for the workflow and the peers on the same points, and removal by visible area for the workflow and a
reverse C2C.

Removal recall by visible area: Σ area · (visible and vacated fraction) over the facets of removed and moved parts
whose twin state is REMOVED, over the same sum for all of them. False removals by area: Σ area · visible fraction
over the facets of unchanged parts (the floor included) whose state is REMOVED, over the same sum for all of them.
States are read as the twin stores them (``read_epoch``); a per-facet removed-area attribute, if one appears, is not
used."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from twin_store import TwinStore

from ..geometry import ReferenceIndex
from ..names import identifier
from ..plugins import Registry
from ..runner import read_dataset
from ..types import ChangeState, Segment
from ..workflow import load_workflow
from .metrics import threshold_candidates
from .peer_runs import C2C_TAU, c2c_methods, m3c2_peers
from .truth import ScanTruth
from .twin_points import composite_from_twin


def weighted_prf(pred: np.ndarray, truth: np.ndarray, weight: np.ndarray | None = None) -> dict[str, Any]:
    """Precision, recall and F1 of a change mask against a truth in [0, 1] (a facet's changed share), each element
    weighted (a facet's area; 1 for points): the plain counts for boolean truth and unit weights."""
    pred = np.asarray(pred, bool)
    t = np.asarray(truth, dtype=np.float64)
    w = np.ones(len(t)) if weight is None else np.asarray(weight, dtype=np.float64)
    tp = float(np.sum(w * t * pred))
    fp = float(np.sum(w * (1 - t) * pred))
    fn = float(np.sum(w * t * ~pred))
    neg = float(np.sum(w * (1 - t)))
    return {"precision": tp / (tp + fp) if tp + fp else None, "recall": tp / (tp + fn) if tp + fn else None,
            "f1": 2 * tp / (2 * tp + fp + fn) if tp + fn else None,
            "false_alarm_rate": fp / neg if neg else None}


def best_tau(distance: np.ndarray, truth: np.ndarray, weight: np.ndarray | None) -> float:
    """The threshold of ``distance > τ`` with the best weighted F1 over the usual candidates (the truth-tuned bound)."""
    cands = threshold_candidates(distance)
    scores = [weighted_prf(distance > t, truth, weight)["f1"] or 0.0 for t in cands]
    return float(cands[int(np.argmax(scores))])


class SceneScans:
    """An epoch's scans as the peers see them: points (facet centroids for meshes), truth, weights, the twin's mask."""

    def __init__(self) -> None:
        self.points: list[np.ndarray] = []
        self.truth: list[np.ndarray] = []
        self.weight: list[np.ndarray] = []
        self.gdt: list[np.ndarray] = []
        self.peer_truth = ScanTruth()
        self.missing: list[str] = []

    def cat(self, name: str) -> np.ndarray:
        """One of the per-scan lists, concatenated."""
        return np.concatenate(getattr(self, name))


def read_scans(wf: Any, sets: dict, registry: Registry) -> SceneScans:
    """Every E1 scan of a suite scene with its truth: per point, or per facet (changed share, area) for meshes."""
    out = SceneScans()
    epoch = next(e for e in wf.model.epochs if e.id == "E1")
    for k, inp in enumerate(epoch.inputs):
        path = wf.input_path(inp)
        key = f"E1_{inp.name or identifier(path.stem)}"
        es = sets[key]
        t = np.load(path.with_name(path.stem + "_truth.npz"))
        mesh = es.kind == "mesh"
        truth = t["facet_changed"] if mesh else t["changed"].astype(np.float64)
        if es.n_elements != len(truth):
            out.missing.append(f"{path.name}: {es.n_elements} twin elements, {len(truth)} in its truth")
            continue
        if mesh:
            ds = read_dataset(path, registry, name="peer", kind="mesh")
            points, weight = ds.points[ds.faces].mean(axis=1), t["facet_area"]
        else:
            points, weight = read_dataset(path, registry, name="peer", kind="points").points, np.ones(len(truth))
        out.points.append(points)
        out.truth.append(truth)
        out.weight.append(weight)
        out.gdt.append(es.state == ChangeState.NEW)
        pt = out.peer_truth
        pt.changed.append(truth >= 0.5)
        pt.points.append(points)
        pt.scanpos.append(np.full(len(points), k + 1, dtype=np.int32))
        pt.keys.append(key)
        pt.viewpoints.append(np.asarray(inp.viewpoints[0], dtype=np.float64))
    return out


def change_scores(scans: SceneScans, store: TwinStore, prev_sets: list, peers: tuple[str, ...],
                  rng: np.random.Generator, notes: list[str], say: Any) -> dict[str, dict[str, Any]]:
    """Change F1 of the twin's mask and of the peers' masks on the same points (weighted by area for meshes)."""
    points, truth, weight = scans.cat("points"), scans.cat("truth"), scans.cat("weight")
    t_bool = truth >= 0.5
    methods: dict[str, dict[str, Any]] = {"gdt": {"label": "gdt (default workflow)", "kind": "ours",
                                                  "changed": scans.cat("gdt"), "params": {}}}
    if "c2c" in peers:
        found = c2c_methods(ReferenceIndex(composite_from_twin(store, "E0")), points, t_bool)
        d = found["c2c_best"]["distance"]
        tau = best_tau(d, truth, weight)  # tuned on the weighted truth the figures use (for points: the same τ)
        found["c2c_best"].update(changed=d > tau, params={"tau": tau}, label=f"C2C/C2M, best τ {tau:.3g} m*")
        methods.update(found)
    if "m3c2" in peers or "m3c2ep" in peers:
        row: dict[str, Any] = {"notes": notes}
        m3c2_peers(methods, peers, prev_sets, points, t_bool, scans.peer_truth, rng, row, say)
        if not np.all(weight == 1.0):
            notes.append("mesh scans: M3C2 runs on the facet centroids; its best radius and registration error are "
                         "chosen on the facets' majority truth, then scored by area")
    out = {}
    for name, m in methods.items():
        idx = m.get("index")
        sel = slice(None) if idx is None else idx
        scores = weighted_prf(m["changed"], truth[sel], weight[sel])
        out[name] = {"label": m["label"], "kind": m["kind"], **scores, "params": m["params"],
                     "evaluated": len(truth[sel])}
    return out


def _removal_flags(et: dict[str, Any], sets: dict, tree: Any) -> tuple[dict[str, dict[str, np.ndarray]], list[str]]:
    """Per CAD part matched in the twin: its truth arrays and the REMOVED flags of the twin and of a reverse C2C."""
    parts, unmatched = {}, []
    for name in sorted(k[len("area__"):] for k in et if k.startswith("area__")):
        es = next((s for k, s in sets.items() if k.startswith("E0_") and k.endswith(f"_{identifier('cad_' + name)}")),
                  None)
        if es is None or es.faces is None or len(es.faces) != len(et[f"area__{name}"]):
            unmatched.append(name)
            continue
        centres = es.points[es.faces].mean(axis=1)
        d, _ = tree.query(centres, distance_upper_bound=C2C_TAU)
        parts[name] = {"area": et[f"area__{name}"], "visible": et[f"visible__{name}"],
                       "visible_removed": et[f"visible_removed__{name}"],
                       "gdt": es.state == ChangeState.REMOVED, "c2c_reverse": ~np.isfinite(d)}
    return parts, unmatched


def removal_scores(et: dict[str, Any], sets: dict, points: np.ndarray) -> dict[str, Any]:
    """Removal recall by visible area and false removals by area, for the twin and a reverse C2C (a facet is
    removed when no scan point lies within C2C_TAU of its centre), with per removed part the recall."""
    from scipy.spatial import cKDTree

    states = et["objects"]
    parts, unmatched = _removal_flags(et, sets, cKDTree(points))
    gone = [n for n in parts if states.get(n) in ("removed", "moved")]
    kept = [n for n in parts if states.get(n) == "unchanged"]
    rem_w = {n: parts[n]["area"] * parts[n]["visible_removed"] for n in gone}
    keep_w = {n: parts[n]["area"] * parts[n]["visible"] for n in kept}
    out: dict[str, Any] = {"removed_visible_area_m2": float(sum(w.sum() for w in rem_w.values())),
                           "unchanged_visible_area_m2": float(sum(w.sum() for w in keep_w.values())),
                           "methods": {}, "parts": {}, "unmatched": unmatched}
    for method in ("gdt", "c2c_reverse"):
        hit = sum(float((w * parts[n][method]).sum()) for n, w in rem_w.items())
        false = sum(float((w * parts[n][method]).sum()) for n, w in keep_w.items())
        out["methods"][method] = {
            "recall": hit / out["removed_visible_area_m2"] if out["removed_visible_area_m2"] > 0 else None,
            "false_removals": false / out["unchanged_visible_area_m2"] if out["unchanged_visible_area_m2"] > 0
            else None}
    for n, w in rem_w.items():
        out["parts"][n] = {"state": states[n], "visible_removed_area_m2": round(float(w.sum()), 6),
                           **{m: round(float((w * parts[n][m]).sum() / w.sum()), 4) if w.sum() > 0 else None
                              for m in ("gdt", "c2c_reverse")}}
    return out


def score_scene(workflow: Path, twin: Path, registry: Registry, peers: tuple[str, ...], rng: np.random.Generator,
                say: Any) -> dict[str, Any]:
    """Change F1 per method and removal by area of one suite scene's twin, against the scene's truth."""
    import json

    wf = load_workflow(workflow, registry)
    store = TwinStore.open(twin)
    sets = {es.key: es for es in store.read_epoch("E1")}
    prev_sets = store.read_epoch("E0")
    scans = read_scans(wf, sets, registry)
    notes: list[str] = [f"not scored: {m}" for m in scans.missing]
    if not scans.points:
        return {"elements": 0, "changed_share": None, "methods": {}, "removal": None, "notes": notes}
    with np.load(workflow.parent / "truth_E1.npz") as t:
        et: dict[str, Any] = {k: t[k] for k in t.files}
    et["objects"] = json.loads(str(et["objects"]))
    methods = change_scores(scans, store, prev_sets, peers, rng, notes, say)
    truth = scans.cat("truth")
    return {"elements": len(truth), "changed_share": float(np.average(truth, weights=scans.cat("weight"))),
            "methods": methods, "removal": removal_scores(et, sets, scans.cat("points")), "notes": notes,
            "moved": moved_scores(json.loads(str(et["displacements"])), store.read_segments("E1"))}


def moved_scores(displacements: dict[str, list[float]], segments: list[Segment]) -> dict[str, Any]:
    """Per moved part: whether a new segment records it as moved, and the error of the recorded displacement (mm);
    and the moved records that name a part that did not move."""
    recorded = {str(g.moved_item): np.asarray(g.displacement) for g in segments if g.moved_item}
    parts = {}
    for name, shift in displacements.items():
        key = next((k for k in recorded if k.endswith(f"_cad_{name}")), None)
        parts[name] = {"recorded": key is not None, "error_mm": None if key is None else
                       round(float(np.linalg.norm(recorded[key] - np.asarray(shift)) * 1000), 2)}
    wrong = [k for k in recorded if not any(k.endswith(f"_cad_{n}") for n in displacements)]
    return {"parts": parts, "wrong_records": wrong}
