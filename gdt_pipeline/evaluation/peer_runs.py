"""The peers run on an epoch's points, as change masks beside the workflow's: cloud-to-cloud / cloud-to-mesh with a
fixed and a best threshold, M3C2 with its documented defaults and with the best radius and registration error, and
M3C2-EP on a subsample."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..geometry import ReferenceIndex
from ..sensors import PRESETS
from . import peers as peer_lib
from .metrics import prf, score_key, sweep, threshold_candidates
from .truth import ScanTruth
from .twin_points import sample_sets

C2C_TAU = 0.01  # m: the fixed threshold reported for the plain-distance peer (a common choice at centimetre noise)
M3C2EP_CORE_POINTS = 2000
PEERS = ("c2c", "m3c2", "m3c2ep")


def c2c_methods(reference: ReferenceIndex, points: np.ndarray, t_changed: np.ndarray) -> dict[str, dict[str, Any]]:
    """The plain-distance peer to the previous composite: with the fixed τ, and with the best τ of a sweep."""
    t0 = time.perf_counter()
    d = reference.nearest(points).distance
    d = np.where(np.isnan(d), np.inf, d)
    dt = time.perf_counter() - t0
    methods = {"c2c_fixed": {"label": f"C2C/C2M, τ {C2C_TAU:g} m", "kind": "peer default", "changed": d > C2C_TAU,
                             "distance": d, "index": None, "seconds": round(dt, 3), "params": {"tau": C2C_TAU}}}
    tau, _ = sweep(d, t_changed, threshold_candidates(d))
    methods["c2c_best"] = {"label": f"C2C/C2M, best τ {tau:.3g} m*", "kind": "peer best", "changed": d > tau,
                           "distance": d, "index": None, "seconds": round(dt, 3), "params": {"tau": tau}}
    return methods


def m3c2_peers(methods: dict, peers: tuple[str, ...], prev_sets: list, points: np.ndarray, t_changed: np.ndarray,
               truth: ScanTruth, rng: np.random.Generator, row: dict, say: Any) -> None:
    """Add the M3C2 and M3C2-EP peers asked for to ``methods`` (a note in ``row`` when py4dgeo is missing)."""
    if not peer_lib.available():
        row["notes"].append("py4dgeo is not installed (pip install 'gdt-pipeline[eval]'): M3C2 peers skipped")
        return
    # Lague et al. (2013): a projection cylinder holding at least ~30 points, normals at twice that scale
    extent = np.ptp(points, axis=0)
    area = max(float(np.sort(extent)[1:].prod()), 1e-6)
    spacing = np.sqrt(area / max(len(points), 1))
    cyl = float(np.sqrt(30.0 / np.pi) * spacing)
    # a CAD solid sampled all round would put its back faces (a 3 mm skin's outer side) into the cylinders: sample
    # only the facets facing a station, the fairest reference a user could give M3C2
    ref = sample_sets(prev_sets, spacing, rng, facing=np.vstack(truth.viewpoints))
    row["notes"].append(f"M3C2 reference: the previous epoch's composite, meshes sampled every {spacing * 1000:.1f} mm "
                        f"on the facets facing a station ({len(ref)} points)")
    max_distance = float(max(0.5, 20 * cyl))
    if "m3c2" in peers:
        say("  M3C2 ...")
        methods.update(_m3c2_methods(ref, points, t_changed, cyl, max_distance))
    if "m3c2ep" in peers:
        say(f"  M3C2-EP on {M3C2EP_CORE_POINTS} core points ...")
        methods["m3c2ep"] = _m3c2ep_method(ref, points, truth, cyl, max_distance, rng)


def _m3c2_methods(ref: np.ndarray, points: np.ndarray, t_changed: np.ndarray, cyl: float, max_distance: float
                  ) -> dict[str, dict[str, Any]]:
    """M3C2 with the documented defaults, and with the best radius and registration error of a sweep on the truth."""
    runs = {}
    for r in (cyl / 2, cyl, 2 * cyl):
        runs[r] = peer_lib.m3c2(ref, points, cyl_radius=r, normal_radii=(2 * r,), max_distance=max_distance)
    base = runs[cyl]
    methods = {"m3c2_default": {"label": f"M3C2, r {cyl * 1000:.3g} mm, reg 0", "kind": "peer default",
                                "changed": base.changed, "distance": base.distance, "index": None,
                                "seconds": round(base.seconds, 3), "params": base.params}}
    best = None
    for r, res in runs.items():
        d = np.abs(np.nan_to_num(res.distance, nan=np.inf))
        for reg in np.concatenate([[0.0], np.geomspace(1e-5, 0.2, 50)]):
            lod = peer_lib.m3c2_lod_with_registration_error(res, reg)
            m = prf(~(d <= lod), t_changed)
            if best is None or score_key(m) > score_key(best[2]):
                best = (r, reg, m, ~(d <= lod), res)
    r, reg, _, mask, res = best
    methods["m3c2_best"] = {"label": f"M3C2, best r {r * 1000:.3g} mm, reg {reg * 1000:.3g} mm*",
                            "kind": "peer best", "changed": mask, "distance": res.distance, "index": None,
                            "seconds": round(sum(x.seconds for x in runs.values()), 3),
                            "params": {"cyl_radius": r, "registration_error": float(reg)}}
    return methods


def _m3c2ep_method(ref: np.ndarray, points: np.ndarray, truth: ScanTruth, cyl: float, max_distance: float,
                   rng: np.random.Generator) -> dict[str, Any]:
    """M3C2-EP with the scanner's noise at the typical range, on a seeded subsample of core points."""
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
    return {"label": f"M3C2-EP, r {cyl * 1000:.3g} mm",
            "kind": "peer default", "changed": res.changed, "distance": res.distance,
            "index": res.core_index, "seconds": round(res.seconds, 3), "params": res.params}
