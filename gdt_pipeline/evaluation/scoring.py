"""Object-level scores of an epoch against its truth: removed geometry per facet, new objects found as clusters of
changed points or as the twin's own segments, and the composite's distance to the true as-is surfaces."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..geometry import ReferenceIndex, distance_to
from ..names import identifier
from ..sensors import PRESETS
from ..types import ChangeState, Segment
from .peer_runs import C2C_TAU
from .truth import ScanTruth, truth_meshes
from .twin_points import sample_sets

CLUSTER_EPS = 0.02  # m: DBSCAN radius that groups changed points into objects


def score_removal(et: dict[str, Any], prev_sets: list, sets: dict, points: np.ndarray, reference: ReferenceIndex
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


def score_new_objects(et: dict[str, Any], methods: dict, points: np.ndarray, truth: ScanTruth
                      ) -> list[dict[str, Any]]:
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


def score_segments(segments: list[Segment], et: dict[str, Any], truth: ScanTruth, prev_sets: list,
                   objects: list[dict[str, Any]]) -> dict[str, Any]:
    """The twin's own segments scored as objects: each new object's best segment (found when mostly on it and
    holding half its points; centroid error to the noise-free centroid of its scanned surface), and removed objects
    found as removed segments."""
    offsets = np.cumsum([0] + [len(c) for c in truth.changed])
    where = {k: int(o) for k, o in zip(truth.keys, offsets[:-1], strict=True)}
    obj, clean = truth.cat("object"), np.vstack(truth.clean)
    new_segs = [g for g in segments if g.kind == "new" and not g.artefact]
    seg_points = [np.concatenate([where[k] + v for k, v in g.members.items() if k in where] or [np.zeros(0, int)])
                  for g in new_segs]
    out: dict[str, Any] = {"new_segments": len(new_segs), "artefacts": sum(g.artefact for g in segments),
                           "removed_segments": sum(g.kind == "removed" and not g.artefact for g in segments)}
    for o in objects:
        if o["truth"] != "new" or not o.get("points"):
            continue
        on = obj == o["name"]
        best = max(range(len(new_segs)), key=lambda i: int(on[seg_points[i]].sum()), default=None)
        found, err = False, None
        if best is not None and on[seg_points[best]].any():
            pts = seg_points[best]
            found = bool(on[pts].mean() > 0.5 and on[pts].sum() >= 0.5 * on.sum())
            err = float(np.linalg.norm(new_segs[best].centroid - clean[on].mean(axis=0)) * 1000)
            solid = et.get("centres", {}).get(o["name"])
            if solid is not None:  # the part's own centre: a one-sided scan sees only the faces towards it
                o["segment_to_solid_centre_mm"] = round(
                    float(np.linalg.norm(new_segs[best].centroid - np.asarray(solid)) * 1000), 2)
                fitted = new_segs[best]
                if fitted.part is not None and fitted.part_centre is not None:  # the part the fusion fitted to it
                    o["fitted_part"] = fitted.part
                    o["fitted_centre_to_solid_centre_mm"] = round(
                        float(np.linalg.norm(fitted.part_centre - np.asarray(solid)) * 1000), 2)
        o.setdefault("methods", {})["gdt_segments"] = {"found": found,
                                                       "centre_error_mm": None if err is None else round(err, 2)}
    removed_names = [n for n, st in et.get("objects", {}).items() if st == "removed"]
    out["removed_found"] = {}
    for name in removed_names:
        keys = [es.key for es in prev_sets if es.key.endswith(f"_{identifier('cad_' + name)}")
                or es.key.endswith(f"_{identifier(name)}")]
        hits = [g for g in segments if g.kind == "removed" and not g.artefact and any(k in g.members for k in keys)]
        out["removed_found"][name] = len(hits)
    return out


def composite_distance(scene_dir: Path, et: dict[str, Any], sets: list, rng: np.random.Generator
                       ) -> dict[str, Any] | None:
    """Distance from the composite (visible elements; meshes sampled) to the true as-is surfaces, in mm."""
    meshes = truth_meshes(scene_dir, et.get("objects", {}))
    if not meshes:
        return None
    pts = sample_sets(sets, 0.005, rng)
    d = distance_to(list(meshes.values()), pts) * 1000.0
    return {"mean_mm": round(float(d.mean()), 3), "p95_mm": round(float(np.quantile(d, 0.95)), 3), "n": len(d),
            "note": "composite points (meshes sampled every 5 mm) to the nearest true as-is surface"}

