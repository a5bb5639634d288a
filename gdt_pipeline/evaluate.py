"""``gdt eval``: run a workflow on a simulated scene and score each epoch against the scene's ground truth, side by
side with the peers on the same data.

Truth lives beside each simulated scan (``<scan>_truth.npz``: per point whether it lies on changed geometry, the
object hit, the noise-free position) and per epoch in the scene directory (``truth_<epoch>.npz``: per facet of the
previous epoch's objects whether it was removed and whether a station could see it, per object its state).

Per as-is epoch this reports, for this workflow and for each peer:

- precision, recall and F1 of the points marked changed, and the false-alarm rate (the only meaningful figure of an
  epoch without true change);
- recall of removed geometry and the false-removal rate on geometry no station could see;
- per new or removed object whether it was found, and for new ones the centre error of the found cluster;
- the composite's distance to the true as-is geometry (mean and 95th percentile).

Peers: cloud-to-cloud / cloud-to-mesh distance to the previous epoch's twin with a fixed threshold, py4dgeo's M3C2
(radius from Lague et al.'s rule of at least 30 points per cylinder, no registration error: the documented defaults)
and M3C2-EP (on a subsample: it runs at a few hundred core points per second). For C2C and M3C2 the best threshold of
a sweep on the truth is also reported: an upper bound no user has.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from twin_store import TwinStore

from .geometry import ReferenceIndex, distance_to
from .names import identifier
from .plugins import Registry, load_registry
from .runner import read_dataset, run_workflow
from .sensors import PRESETS
from .types import ChangeState, Composite, CompositeItem, Dataset
from .workflow import load_workflow

C2C_TAU = 0.01  # m: the fixed threshold reported for the plain-distance peer (a common choice at centimetre noise)
M3C2EP_CORE_POINTS = 2000
CLUSTER_EPS = 0.02  # m: DBSCAN radius that groups changed points into objects
PEERS = ("c2c", "m3c2", "m3c2ep")


def _prf(pred: np.ndarray, truth: np.ndarray) -> dict[str, Any]:
    """Precision, recall, F1 and false-alarm rate of a change mask; None where the ratio is undefined."""
    pred, truth = np.asarray(pred, bool), np.asarray(truth, bool)
    tp = int(np.sum(pred & truth))
    fp = int(np.sum(pred & ~truth))
    fn = int(np.sum(~pred & truth))
    negatives = int(np.sum(~truth))
    return {"precision": tp / (tp + fp) if tp + fp else None,
            "recall": tp / (tp + fn) if tp + fn else None,
            "f1": 2 * tp / (2 * tp + fp + fn) if tp + fn else None,
            "false_alarm_rate": fp / negatives if negatives else None,
            "tp": tp, "fp": fp, "fn": fn, "evaluated_points": len(truth)}


def _score_key(m: dict[str, Any]) -> float:
    """What a sweep maximises: F1 where there is true change, else the fewest false alarms."""
    return m["f1"] if m["f1"] is not None else -(m["false_alarm_rate"] or 0.0)


def _sweep(margin: np.ndarray, truth: np.ndarray, candidates: np.ndarray) -> tuple[float, dict[str, Any]]:
    """Best threshold t of the rule ``margin > t`` over the candidates, scored on the truth."""
    best = max(((float(t), _prf(~(margin <= t), truth)) for t in candidates), key=lambda x: _score_key(x[1]))
    return best


def _candidates(values: np.ndarray) -> np.ndarray:
    """Thresholds spanning the finite values: log-spaced plus quantiles, so a rare change still gets a candidate."""
    v = values[np.isfinite(values) & (values > 0)]
    if not v.size:
        return np.array([0.0])
    logs = np.geomspace(max(v.min(), 1e-6), v.max(), 80)
    return np.unique(np.concatenate([logs, np.quantile(v, np.linspace(0.0, 1.0, 81))]))


def _composite_from_twin(store: TwinStore, epoch: str) -> Composite:
    items = []
    for es in store.read_epoch(epoch):
        ds = Dataset(es.key, "as-is", es.points, faces=es.faces)
        items.append(CompositeItem(es.key, ds, epoch, es.state, es.score.astype(np.float64), es.source_epoch,
                                   es.visible))
    return Composite(tuple(items))


def _sample_sets(sets: list, spacing: float, rng: np.random.Generator, *, visible_only: bool = True,
                 facing: np.ndarray | None = None) -> np.ndarray:
    """Points of the given element sets: point sets as they are, meshes sampled at ``spacing``; with ``facing``
    (station positions), only facets that face one of them, as a scanner would have seen the part."""
    import trimesh

    out = []
    for es in sets:
        keep = es.visible.astype(bool) if visible_only else np.ones(es.n_elements, bool)
        if es.kind == "mesh" and facing is not None and keep.any():
            tri = es.points[es.faces]
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            centre = tri.mean(axis=1)
            keep &= np.any(np.einsum("fj,sfj->sf", normal, facing[:, None, :] - centre[None]) > 0, axis=0)
        if not keep.any():
            continue
        if es.kind == "points":
            out.append(es.points[keep])
            continue
        mesh = trimesh.Trimesh(es.points, es.faces[keep], process=False)
        n = max(int(mesh.area / spacing**2), 1)
        pts, _ = trimesh.sample.sample_surface(mesh, n, seed=int(rng.integers(2**31)))
        out.append(np.asarray(pts))
    return np.vstack(out) if out else np.zeros((0, 3))


def _truth_meshes(scene_dir: Path, states: dict[str, str]) -> dict[str, Any]:
    """The true meshes of the objects present in an epoch, from the scene's CAD and truth OBJ files."""
    import trimesh

    out = {}
    for name, state in states.items():
        if state in ("removed", "absent"):
            continue
        for stem in (f"cad_{name}", f"truth_{name}"):
            path = scene_dir / f"{stem}.obj"
            if path.is_file():
                out[name] = trimesh.load(path, force="mesh", process=False)
                break
    return out


class _ScanTruth:
    """The per-point truth of an epoch's scans, concatenated in input order."""

    def __init__(self) -> None:
        self.changed: list[np.ndarray] = []
        self.points: list[np.ndarray] = []
        self.clean: list[np.ndarray] = []
        self.object: list[np.ndarray] = []
        self.scanpos: list[np.ndarray] = []
        self.keys: list[str] = []
        self.viewpoints: list[np.ndarray] = []
        self.profile: str | None = None

    def cat(self, name: str) -> np.ndarray:
        return np.concatenate(getattr(self, name)) if getattr(self, name) else np.zeros(0)


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
        row, arr = _evaluate_epoch(wf, store, epochs[index - 1].id, epoch, registry, peers, rng, say)
        if row.get("scene"):
            result["scene"] = row.pop("scene")
        result["epochs"].append(row)
        if arr:
            arrays[epoch.id] = arr
    result["seconds"] = round(time.perf_counter() - started, 2)
    return result, arrays


def _gdt_seconds(store: TwinStore, epoch: str) -> float | None:
    try:
        prov = store.provenance(epoch)
    except Exception:  # an older twin without the record: the time is simply not known
        return None
    stages = prov.get("stages", [])
    total = sum(float(s.get("seconds", 0.0)) for s in stages if isinstance(s, dict))
    return round(total, 3) if stages else None


def _evaluate_epoch(wf: Any, store: TwinStore, prev_id: str, epoch: Any, registry: Registry,
                    peers: tuple[str, ...], rng: np.random.Generator, say: Any) -> tuple[dict[str, Any], dict]:
    sets = {es.key: es for es in store.read_epoch(epoch.id)}
    prev_sets = store.read_epoch(prev_id)
    truth = _ScanTruth()
    pred, missing = [], []
    scene_dir = None
    for k, inp in enumerate(epoch.inputs):
        path = wf.input_path(inp)
        tpath = path.with_name(path.stem + "_truth.npz")
        if not tpath.is_file():
            missing.append(str(path))
            continue
        scene_dir = path.parent
        key = f"{epoch.id}_{inp.name or identifier(path.stem)}"
        t = np.load(tpath)
        es = sets[key]
        if es.n_elements != len(t["changed"]):
            missing.append(f"{path} (its elements are not its points: e.g. voxel Gaussians)")
            continue
        pred.append(es.state == ChangeState.NEW)
        raw = read_dataset(path, registry, name="peer", kind="points")
        names = [str(n) for n in t["object_names"]]
        truth.changed.append(t["changed"].astype(bool))
        truth.points.append(raw.points)
        truth.clean.append(t["clean"])
        truth.object.append(np.array(names, dtype=object)[t["object_id"]])
        truth.scanpos.append(np.full(len(raw.points), k + 1, dtype=np.int32))
        truth.keys.append(key)
        vp = inp.viewpoints[0] if inp.viewpoints else json.loads(
            path.with_name(path.stem + "_pose.json").read_text())["viewpoint"]
        truth.viewpoints.append(np.asarray(vp, dtype=np.float64))
        pose = path.with_name(path.stem + "_pose.json")
        if pose.is_file():
            scanner = json.loads(pose.read_text()).get("scanner") or {}
            truth.profile = scanner.get("profile", truth.profile)
    row: dict[str, Any] = {"epoch": epoch.id, "missing_truth": missing, "methods": [], "notes": []}
    if not pred:
        return row, {}
    t_changed, points = truth.cat("changed").astype(bool), np.vstack(truth.points)
    epoch_truth = _epoch_truth(scene_dir, epoch.id)
    if epoch_truth is not None and (scene_dir / "scene.json").is_file():
        row["scene"] = json.loads((scene_dir / "scene.json").read_text()).get("scene", scene_dir.name)
    row.update(points=len(t_changed), changed=int(t_changed.sum()))
    methods: dict[str, dict[str, Any]] = {}
    gdt_mask = np.concatenate(pred)
    methods["gdt"] = {"label": "gdt (this workflow)", "kind": "ours", "changed": gdt_mask, "distance": None,
                      "index": None, "seconds": _gdt_seconds(store, epoch.id), "params": {}}
    reference = ReferenceIndex(_composite_from_twin(store, prev_id))
    if "c2c" in peers:
        t0 = time.perf_counter()
        d = reference.nearest(points).distance
        d = np.where(np.isnan(d), np.inf, d)
        dt = time.perf_counter() - t0
        methods["c2c_fixed"] = {"label": f"C2C/C2M, τ {C2C_TAU:g} m", "kind": "peer default", "changed": d > C2C_TAU,
                                "distance": d, "index": None, "seconds": round(dt, 3), "params": {"tau": C2C_TAU}}
        tau, _ = _sweep(d, t_changed, _candidates(d))
        methods["c2c_best"] = {"label": f"C2C/C2M, best τ {tau:.3g} m*", "kind": "peer best", "changed": d > tau,
                               "distance": d, "index": None, "seconds": round(dt, 3), "params": {"tau": tau}}
    if "m3c2" in peers or "m3c2ep" in peers:
        _m3c2_peers(methods, peers, prev_sets, points, t_changed, truth, rng, row, say)
    for name, m in methods.items():
        idx = m["index"]
        scores = _prf(m["changed"], t_changed if idx is None else t_changed[idx])
        row["methods"].append({"name": name, "label": m["label"], "kind": m["kind"], **scores,
                               "seconds": m["seconds"], "params": m["params"]})
    if epoch_truth is not None:
        row["removal"] = _removal(epoch_truth, prev_sets, sets, points, reference)
        row["objects"] = _objects(epoch_truth, methods, points, truth)
        row["segments"] = _segment_objects(store.read_segments(epoch.id), epoch_truth, truth, prev_sets,
                                           row["objects"])
        row["composite"] = _composite_distance(scene_dir, epoch_truth, list(sets.values()), rng)
    else:
        row["removal"], row["objects"], row["composite"] = None, [], None
        row["notes"].append(f"no truth_{epoch.id}.npz in the scene directory: removal, objects and composite skipped")
    arr = {"points": points, "truth": t_changed,
           "methods": {n: {"changed": m["changed"], "distance": m["distance"], "index": m["index"]}
                       for n, m in methods.items()}}
    return row, arr


def _epoch_truth(scene_dir: Path | None, epoch_id: str) -> dict[str, Any] | None:
    if scene_dir is None or not (scene_dir / f"truth_{epoch_id}.npz").is_file():
        return None
    t = np.load(scene_dir / f"truth_{epoch_id}.npz")
    out: dict[str, Any] = {k: t[k] for k in t.files}
    out["objects"] = json.loads(str(t["objects"])) if "objects" in t.files else {}
    out["centres"] = json.loads(str(t["centres"])) if "centres" in t.files else {}
    return out


def _m3c2_peers(methods: dict, peers: tuple[str, ...], prev_sets: list, points: np.ndarray, t_changed: np.ndarray,
                truth: _ScanTruth, rng: np.random.Generator, row: dict, say: Any) -> None:
    from . import peers as peer_lib

    if not peer_lib.available():
        row["notes"].append("py4dgeo is not installed (pip install 'gdt-pipeline[peers]'): M3C2 peers skipped")
        return
    # Lague et al. (2013): a projection cylinder holding at least ~30 points, normals at twice that scale
    extent = np.ptp(points, axis=0)
    area = max(float(np.sort(extent)[1:].prod()), 1e-6)
    spacing = np.sqrt(area / max(len(points), 1))
    cyl = float(np.sqrt(30.0 / np.pi) * spacing)
    # a CAD solid sampled all round would put its back faces (a 3 mm skin's outer side) into the cylinders: sample
    # only the facets facing a station, the fairest reference a user could give M3C2
    ref = _sample_sets(prev_sets, spacing, rng, facing=np.vstack(truth.viewpoints))
    row["notes"].append(f"M3C2 reference: the previous epoch's composite, meshes sampled every {spacing * 1000:.1f} mm "
                        f"on the facets facing a station ({len(ref)} points)")
    max_distance = float(max(0.5, 20 * cyl))
    if "m3c2" in peers:
        say("  M3C2 ...")
        runs = {}
        for r in (cyl / 2, cyl, 2 * cyl):
            runs[r] = peer_lib.m3c2(ref, points, cyl_radius=r, normal_radii=(2 * r,), max_distance=max_distance)
        base = runs[cyl]
        methods["m3c2_default"] = {"label": f"M3C2, r {cyl * 1000:.3g} mm, reg 0", "kind": "peer default",
                                   "changed": base.changed, "distance": base.distance, "index": None,
                                   "seconds": round(base.seconds, 3), "params": base.params}
        best = None
        for r, res in runs.items():
            d = np.abs(np.nan_to_num(res.distance, nan=np.inf))
            for reg in np.concatenate([[0.0], np.geomspace(1e-5, 0.2, 50)]):
                lod = peer_lib.m3c2_lod_with_registration_error(res, reg)
                m = _prf(~(d <= lod), t_changed)
                if best is None or _score_key(m) > _score_key(best[2]):
                    best = (r, reg, m, ~(d <= lod), res)
        r, reg, _, mask, res = best
        methods["m3c2_best"] = {"label": f"M3C2, best r {r * 1000:.3g} mm, reg {reg * 1000:.3g} mm*",
                                "kind": "peer best", "changed": mask, "distance": res.distance, "index": None,
                                "seconds": round(sum(x.seconds for x in runs.values()), 3),
                                "params": {"cyl_radius": r, "registration_error": float(reg)}}
    if "m3c2ep" in peers:
        say(f"  M3C2-EP on {M3C2EP_CORE_POINTS} core points ...")
        profile = PRESETS.get(truth.profile or "", PRESETS["structured_light"])
        origins = np.vstack(truth.viewpoints)
        typical = float(np.median(np.linalg.norm(points - origins[truth.cat("scanpos").astype(int) - 1], axis=1)))
        s_r, s_l = profile.sigmas(np.array([typical]), None, "m")
        # the reference is the previous composite (CAD, or scans of several epochs fused): one pseudo origin at the
        # query's mean station with a negligible range sigma, since its own uncertainty is not a scanner's
        res = peer_lib.m3c2_ep(ref, points, reference_origins=origins.mean(axis=0, keepdims=True),
                               query_origins=origins, reference_scanpos=np.ones(len(ref), np.int32),
                               query_scanpos=truth.cat("scanpos").astype(np.int32), cyl_radius=cyl,
                               normal_radii=(2 * cyl,), max_distance=max_distance, sigma_range=float(s_r[0]),
                               sigma_scan=float(s_l[0] / typical), sigma_yaw=float(s_l[0] / typical),
                               reference_sigmas=(1e-6, 1e-8, 1e-8), max_core_points=M3C2EP_CORE_POINTS,
                               seed=int(rng.integers(2**31)))
        methods["m3c2ep"] = {"label": f"M3C2-EP, r {cyl * 1000:.3g} mm",
                             "kind": "peer default", "changed": res.changed, "distance": res.distance,
                             "index": res.core_index, "seconds": round(res.seconds, 3), "params": res.params}


def _removal(et: dict[str, Any], prev_sets: list, sets: dict, points: np.ndarray, reference: ReferenceIndex
             ) -> dict[str, Any] | None:
    """Recall of removed facets and false removals on facets no station saw, for the twin and a reverse C2C."""
    names = [k[len("removed__"):] for k in et if k.startswith("removed__")]
    if not names:
        return None
    from scipy.spatial import cKDTree

    tree = cKDTree(points)
    removed_t, view_t, gdt_r, c2c_r = [], [], [], []
    unmatched: list[str] = []
    per_object: dict[str, Any] = {}
    for name in names:
        key = next((es.key for es in prev_sets if es.key.endswith(f"_{identifier('cad_' + name)}")
                    or es.key.endswith(f"_{identifier(name)}")), None)
        if key is None or key not in sets or sets[key].faces is None or \
                len(sets[key].faces) != len(et[f"removed__{name}"]):
            unmatched.append(name)
            continue
        es = sets[key]
        removed_t.append(et[f"removed__{name}"].astype(bool))
        view_t.append(et[f"in_view__{name}"].astype(bool))
        gdt_r.append(es.state == ChangeState.REMOVED)
        centres = es.points[es.faces].mean(axis=1)
        d, _ = tree.query(centres, distance_upper_bound=C2C_TAU)
        c2c_r.append(~np.isfinite(d))
        seen = removed_t[-1] & view_t[-1]
        if seen.any():  # a removed object is found when most of what could be seen of it is marked removed
            per_object[name] = {m: {"facets_seen": int(seen.sum()), "marked": int(f[seen].sum()),
                                    "found": bool(f[seen].mean() >= 0.5)}
                                for m, f in (("gdt", gdt_r[-1]), ("c2c_reverse", c2c_r[-1]))}
    if not removed_t:
        return {"note": f"no twin element set matches the truth objects {unmatched}"}
    rem, view = np.concatenate(removed_t), np.concatenate(view_t)
    out: dict[str, Any] = {"removed_facets": int(rem.sum()), "removed_in_view": int((rem & view).sum()),
                           "occluded_facets": int((~view & ~rem).sum()), "methods": {}, "objects": per_object}
    for label, flag in (("gdt", np.concatenate(gdt_r)), ("c2c_reverse", np.concatenate(c2c_r))):
        out["methods"][label] = {
            "recall": float(flag[rem & view].mean()) if (rem & view).any() else None,
            "false_removal_rate_occluded": float(flag[~view & ~rem].mean()) if (~view & ~rem).any() else None,
            "false_removal_rate_seen": float(flag[view & ~rem].mean()) if (view & ~rem).any() else None}
    gdt = out["methods"]["gdt"]
    out["recall"], out["false_removal_rate"] = gdt["recall"], gdt["false_removal_rate_occluded"]
    out["note"] = (f"recall over removed facets a station could see; false removals over unseen, unremoved facets; "
                   f"c2c_reverse: a facet is removed when no scan point lies within {C2C_TAU:g} m of its centre")
    if unmatched:
        out["note"] += f"; not matched to the twin: {unmatched}"
    return out


def _objects(et: dict[str, Any], methods: dict, points: np.ndarray, truth: _ScanTruth) -> list[dict[str, Any]]:
    """Per new object: found (a cluster of changed points mostly on it, holding half its points) and the distance
    from that cluster's centroid to the noise-free centroid of the object's scanned surface."""
    import open3d as o3d

    obj = truth.cat("object")
    clean = np.vstack(truth.clean)
    # the clustering radius grows with the sensor's range noise, or a noisy scan falls apart into fragments
    profile = PRESETS.get(truth.profile or "", None)
    eps = CLUSTER_EPS
    if profile is not None and truth.viewpoints:
        station = np.vstack(truth.viewpoints)[truth.cat("scanpos").astype(int) - 1]
        rng_typ = float(np.median(np.linalg.norm(points - station, axis=1)))
        eps = max(CLUSTER_EPS, 1.5 * float(profile.sigmas(np.array([rng_typ]), None, "m")[0][0]))
    out = []
    new = [n for n, s in et.get("objects", {}).items() if s == "new"]
    for name in new:
        on = obj == name
        if not on.any():
            out.append({"name": name, "truth": "new", "points": 0, "note": "not in any station's view"})
            continue
        visible_centre = clean[on].mean(axis=0)
        entry: dict[str, Any] = {"name": name, "truth": "new", "points": int(on.sum()), "methods": {},
                                 "cluster_eps_m": round(eps, 4)}
        for mname, m in methods.items():
            if m["index"] is not None:
                continue  # a subsample cannot be clustered like the full cloud
            flagged = np.flatnonzero(m["changed"])
            found, err = False, None
            if flagged.size:
                pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[flagged]))
                labels = np.asarray(pcd.cluster_dbscan(eps=eps, min_points=5))
                own = labels[on[flagged]]
                own = own[own >= 0]
                if own.size:
                    lab = np.bincount(own).argmax()
                    members = flagged[labels == lab]
                    found = bool(on[members].mean() > 0.5 and np.isin(np.flatnonzero(on), members).mean() >= 0.5)
                    err = float(np.linalg.norm(points[members].mean(axis=0) - visible_centre) * 1000)
            entry["methods"][mname] = {"found": found, "centre_error_mm": round(err, 2) if err is not None else None}
        out.append(entry)
    for name in (n for n, s in et.get("objects", {}).items() if s == "removed"):
        out.append({"name": name, "truth": "removed",
                    "note": "removal is scored per facet under 'removal' (found: recall over its visible facets)"})
    return out


def _segment_objects(segments: list[dict], et: dict[str, Any], truth: _ScanTruth, prev_sets: list,
                     objects: list[dict[str, Any]]) -> dict[str, Any]:
    """The twin's own segments scored as objects: each new object's best segment (found when mostly on it and
    holding half its points; centroid error to the noise-free centroid of its scanned surface), and removed objects
    found as removed segments."""
    offsets = np.cumsum([0] + [len(c) for c in truth.changed])
    where = {k: int(o) for k, o in zip(truth.keys, offsets[:-1], strict=True)}
    obj, clean = truth.cat("object"), np.vstack(truth.clean)
    new_segs = [g for g in segments if g["kind"] == "new" and not g["artefact"]]
    seg_points = [np.concatenate([where[k] + v for k, v in g["members"].items() if k in where] or [np.zeros(0, int)])
                  for g in new_segs]
    out: dict[str, Any] = {"new_segments": len(new_segs), "artefacts": sum(g["artefact"] for g in segments),
                           "removed_segments": sum(g["kind"] == "removed" and not g["artefact"] for g in segments)}
    for o in objects:
        if o["truth"] != "new" or not o.get("points"):
            continue
        on = obj == o["name"]
        best = max(range(len(new_segs)), key=lambda i: int(on[seg_points[i]].sum()), default=None)
        found, err = False, None
        if best is not None and on[seg_points[best]].any():
            pts = seg_points[best]
            found = bool(on[pts].mean() > 0.5 and on[pts].sum() >= 0.5 * on.sum())
            err = float(np.linalg.norm(new_segs[best]["centroid"] - clean[on].mean(axis=0)) * 1000)
            solid = et.get("centres", {}).get(o["name"])
            if solid is not None:  # the part's own centre: a one-sided scan sees only the faces towards it
                o["segment_to_solid_centre_mm"] = round(
                    float(np.linalg.norm(new_segs[best]["centroid"] - np.asarray(solid)) * 1000), 2)
                if new_segs[best].get("part") is not None:  # the catalogue part the fusion fitted to the segment
                    o["fitted_part"] = new_segs[best]["part"]
                    o["fitted_centre_to_solid_centre_mm"] = round(
                        float(np.linalg.norm(new_segs[best]["part_centre"] - np.asarray(solid)) * 1000), 2)
        o.setdefault("methods", {})["gdt_segments"] = {"found": found,
                                                       "centre_error_mm": None if err is None else round(err, 2)}
    removed_names = [n for n, st in et.get("objects", {}).items() if st == "removed"]
    out["removed_found"] = {}
    for name in removed_names:
        keys = [es.key for es in prev_sets if es.key.endswith(f"_{identifier('cad_' + name)}")
                or es.key.endswith(f"_{identifier(name)}")]
        hits = [g for g in segments if g["kind"] == "removed" and not g["artefact"] and
                any(k in g["members"] for k in keys)]
        out["removed_found"][name] = len(hits)
    return out


def _composite_distance(scene_dir: Path, et: dict[str, Any], sets: list, rng: np.random.Generator
                        ) -> dict[str, Any] | None:
    """Distance from the composite (visible elements; meshes sampled) to the true as-is surfaces, in mm."""
    meshes = _truth_meshes(scene_dir, et.get("objects", {}))
    if not meshes:
        return None
    pts = _sample_sets(sets, 0.005, rng)
    d = distance_to(list(meshes.values()), pts) * 1000.0
    return {"mean_mm": round(float(d.mean()), 3), "p95_mm": round(float(np.quantile(d, 0.95)), 3), "n": len(d),
            "note": "composite points (meshes sampled every 5 mm) to the nearest true as-is surface"}


def format_table(result: dict[str, Any]) -> str:
    """The results as a plain-text table."""
    def f(x: Any, spec: str = ".4f") -> str:
        return "–" if x is None else format(x, spec)

    lines = [f"{result['workflow']} -> {result['twin']}",
             f"{'epoch':<6} {'points':>8} {'changed':>8}  {'method':<40} {'prec.':>7} {'recall':>7} {'F1':>7} "
             f"{'FA rate':>8} {'s':>7}"]
    for row in result["epochs"]:
        if not row.get("methods"):
            lines.append(f"{row['epoch']:<6} no ground truth ({'; '.join(row['missing_truth'])})")
            continue
        for i, m in enumerate(row["methods"]):
            head = f"{row['epoch']:<6} {row['points']:>8} {row['changed']:>8}" if i == 0 else " " * 24
            pts = "" if m["evaluated_points"] == row["points"] else f" [{m['evaluated_points']} pts]"
            lines.append(f"{head}  {(m['label'] + pts)[:40]:<40} {f(m['precision']):>7} {f(m['recall']):>7} "
                         f"{f(m['f1']):>7} {f(m['false_alarm_rate']):>8} {f(m['seconds'], '.1f'):>7}")
        rem = row.get("removal")
        if rem and "methods" in rem:
            for label, r in rem["methods"].items():
                lines.append(f"{'':24}  removal {label:<12} recall {f(r['recall'])} (of {rem['removed_in_view']} "
                             f"visible removed facets), false removals on occluded "
                             f"{f(r['false_removal_rate_occluded'])} (of {rem['occluded_facets']})")
        for name, per in (rem or {}).get("objects", {}).items():
            found = ", ".join(f"{k}: {'found' if v['found'] else 'missed'} ({v['marked']}/{v['facets_seen']} visible "
                              f"facets)" for k, v in per.items())
            lines.append(f"{'':24}  removed {name}: {found}")
        for o in row.get("objects", []):
            if o["truth"] != "new" or "methods" not in o:
                continue
            found = ", ".join(f"{k}: {'found' if v['found'] else 'missed'}"
                              + (f" {v['centre_error_mm']:.2f} mm" if v["found"] else "")
                              for k, v in o["methods"].items())
            solid = (f"; segment centroid to the part's solid centre {o['segment_to_solid_centre_mm']:.1f} mm"
                     if o.get("segment_to_solid_centre_mm") is not None else "")
            if o.get("fitted_part") is not None:
                solid += (f"; fitted {o['fitted_part']!r} centre to the solid centre "
                          f"{o['fitted_centre_to_solid_centre_mm']:.2f} mm")
            elif o.get("segment_to_solid_centre_mm") is not None:
                solid += "; no part fitted"
            lines.append(f"{'':24}  new {o['name']} ({o['points']} pts): {found}{solid}")
        if row.get("segments"):
            g = row["segments"]
            lines.append(f"{'':24}  twin segments: {g['new_segments']} new, {g['removed_segments']} removed, "
                         f"{g['artefacts']} artefacts; removed objects as removed segments: {g['removed_found']}")
        if row.get("composite"):
            c = row["composite"]
            lines.append(f"{'':24}  composite to true as-is geometry: mean {c['mean_mm']:.2f} mm, "
                         f"p95 {c['p95_mm']:.2f} mm")
    lines.append("* best threshold of a sweep on the truth: an upper bound no user has; FA rate: flagged share of "
                 "unchanged points")
    return "\n".join(lines)


def with_fusion(workflow: str | Path, fusion: str) -> Path:
    """A copy of the workflow, beside it (so its relative paths hold), whose fusion stage is ``fusion`` and whose
    twin goes to ``<twin>_<fusion>``: to compare fusion policies on the same data. The caller deletes it."""
    import yaml

    path = Path(workflow)
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    stages = [s for s in doc.get("stages", []) if s.get("uses") in FUSIONS]
    if not stages:
        raise ValueError(f"{path}: no fusion stage to replace (one of {', '.join(FUSIONS)})")
    for st in stages:
        st["uses"] = fusion
        st.pop("with", None)  # the policies' own parameters differ; the segmentation defaults hold
    doc["twin"] = f"{doc.get('twin', 'twin')}_{fusion}"
    out = path.with_name(f".{path.stem}.{fusion}.yaml")
    out.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return out


FUSIONS = ("most_reliable", "keep_unchanged", "keep_reference", "replace_in_view")
SCENE_DIRS = {"paper_test_scene": "paper-test-scene", "fuselage": "fuselage", "test_scene": "test-scene"}


def missing_scene(workflow: str | Path, registry: Registry | None = None) -> tuple[str | None, Path] | None:
    """None when the workflow's inputs exist; else (the bundled scene that provides them or None, its directory).

    Reads the YAML directly: loading the workflow would (rightly) reject the missing files."""
    import yaml

    path = Path(workflow)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError):
        return None  # loading the workflow reports it, with the line
    for epoch in doc.get("epochs") or []:
        for inp in (epoch or {}).get("inputs") or []:
            ref = inp.get("path") if isinstance(inp, dict) else inp
            if not isinstance(ref, str):
                continue
            file = Path(ref) if Path(ref).is_absolute() else (path.parent / ref)
            if not file.exists():
                return SCENE_DIRS.get(file.parent.name), file.parent
    return None
