"""The peers ``gdt eval`` runs side by side with a workflow: py4dgeo's M3C2 and M3C2-EP (the optional ``eval``
extra), on the same points.

Both compare a reference cloud (the previous epoch: a scan, or CAD meshes sampled densely) with a query scan and
answer per core point whether it moved more than the level of detection (LoD). Core points are the query points
themselves, so the answer is per query point, like the workflow's. A core point with no neighbours in either cloud
gets a NaN distance and counts as changed: there is no counterpart, so it is new geometry.

Measured facts about py4dgeo 1.2.0 (checked in tests/test_peers.py):

- M3C2's LoD is 1.96·(√(σ₁²/n₁ + σ₂²/n₂) + registration_error), so a registration-error sweep needs one run per
  cylinder radius: ``m3c2_lod_with_registration_error`` shifts the LoD of a run made with none;
- M3C2-EP's distance is n·(p₁ − p₂), the opposite sign of M3C2's n·(p₂ − p₁); it is flipped here. It needs a
  per-point ``scanpos_id`` (int32, 1-based) in ``additional_dimensions`` and ``scanpos_info`` (origin, sigma_range,
  sigma_scan, sigma_yaw as Python floats) on each epoch, plus ``tfM`` (3x4), ``Cxx`` (12x12) and ``refPointMov``;
  it processes a few hundred core points per second in Python worker processes, so it runs on a seeded subsample.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import logging
import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

Z95 = 1.96  # py4dgeo's two-sided 95 % factor in the M3C2 LoD


@dataclass(frozen=True)
class PeerResult:
    """Per core point: signed distance (query minus reference, along the normal), level of detection, change."""

    distance: np.ndarray
    lod: np.ndarray
    changed: np.ndarray
    core_index: np.ndarray
    seconds: float
    params: dict[str, Any] = field(default_factory=dict)
    spread: np.ndarray | None = None  # √(σ₁²/n₁ + σ₂²/n₂), the part of the LoD the data gives


def available() -> bool:
    """Whether py4dgeo is installed."""
    return importlib.util.find_spec("py4dgeo") is not None


def _py4dgeo() -> Any:
    try:
        import py4dgeo
    except ImportError as exc:  # the optional extra is missing: say how to get it
        raise ImportError("the M3C2 peers need py4dgeo: pip install 'gdt-pipeline[eval]'") from exc
    logging.getLogger("py4dgeo").setLevel(logging.WARNING)
    with contextlib.suppress(Exception):  # older versions have no thread setting
        py4dgeo.set_num_threads(max(1, os.cpu_count() or 1))
    return py4dgeo


def _changed(distance: np.ndarray, lod: np.ndarray) -> np.ndarray:
    return ~(np.abs(distance) <= lod)  # NaN (no counterpart) is change


def m3c2(reference: np.ndarray, query: np.ndarray, *, cyl_radius: float, normal_radii: tuple[float, ...],
         max_distance: float, registration_error: float = 0.0) -> PeerResult:
    """py4dgeo's M3C2 with every query point as a core point (epoch 1: reference, epoch 2: query)."""
    py4dgeo = _py4dgeo()
    reference = np.ascontiguousarray(reference, dtype=np.float64)
    query = np.ascontiguousarray(query, dtype=np.float64)
    started = time.perf_counter()
    e1, e2 = py4dgeo.Epoch(reference), py4dgeo.Epoch(query)
    algo = py4dgeo.M3C2(epochs=(e1, e2), corepoints=query, cyl_radius=float(cyl_radius),
                        normal_radii=[float(r) for r in normal_radii], max_distance=float(max_distance),
                        registration_error=float(registration_error))
    with contextlib.redirect_stdout(io.StringIO()):
        distance, unc = algo.run()
    seconds = time.perf_counter() - started
    lod = np.asarray(unc["lodetection"], dtype=np.float64)
    spread = lod / Z95 - registration_error
    return PeerResult(distance=np.asarray(distance, dtype=np.float64), lod=lod, changed=_changed(distance, lod),
                      core_index=np.arange(len(query)), seconds=seconds, spread=spread,
                      params={"cyl_radius": float(cyl_radius), "normal_radii": [float(r) for r in normal_radii],
                              "max_distance": float(max_distance), "registration_error": float(registration_error)})


def m3c2_lod_with_registration_error(result: PeerResult, registration_error: float) -> np.ndarray:
    """The LoD the same M3C2 run would have had with another ``registration_error`` (linear in it)."""
    if result.spread is None:
        raise ValueError("only M3C2 results carry the spread the LoD is made of")
    return Z95 * (result.spread + registration_error)


def m3c2_ep(reference: np.ndarray, query: np.ndarray, *, reference_origins: np.ndarray, query_origins: np.ndarray,
            reference_scanpos: np.ndarray, query_scanpos: np.ndarray, cyl_radius: float,
            normal_radii: tuple[float, ...], max_distance: float, sigma_range: float, sigma_scan: float,
            sigma_yaw: float, reference_sigmas: tuple[float, float, float] | None = None,
            max_core_points: int = 2000, seed: int = 0, registration_cov: np.ndarray | None = None) -> PeerResult:
    """py4dgeo's M3C2-EP (error propagation from the scanners' range and angle noise) on a subsample of the query.

    ``reference_sigmas`` (range, scan, yaw) default to the query's; for a CAD reference pass tiny ones. The result
    holds ``len(core_index)`` entries, ``core_index`` indexing the query.
    """
    py4dgeo = _py4dgeo()
    rng = np.random.default_rng(seed)
    n = len(query)
    core_index = np.sort(rng.choice(n, size=min(max_core_points, n), replace=False))
    reference = np.ascontiguousarray(reference, dtype=np.float64)
    query = np.ascontiguousarray(query, dtype=np.float64)

    def epoch(cloud: np.ndarray, scanpos: np.ndarray, origins: np.ndarray, sig: tuple[float, float, float]) -> Any:
        dims = np.empty(len(cloud), dtype=[("scanpos_id", "<i4")])
        dims["scanpos_id"] = np.asarray(scanpos, dtype=np.int32)
        e = py4dgeo.Epoch(cloud, additional_dimensions=dims)
        e.scanpos_info = [{"origin": [float(v) for v in o], "sigma_range": float(sig[0]),
                           "sigma_scan": float(sig[1]), "sigma_yaw": float(sig[2])} for o in np.atleast_2d(origins)]
        return e

    q_sig = (sigma_range, sigma_scan, sigma_yaw)
    e1 = epoch(reference, reference_scanpos, reference_origins, reference_sigmas or q_sig)
    e2 = epoch(query, query_scanpos, query_origins, q_sig)
    tfm = np.hstack([np.eye(3), np.zeros((3, 1))])
    started = time.perf_counter()
    algo = py4dgeo.M3C2EP(epochs=(e1, e2), corepoints=query[core_index], cyl_radius=float(cyl_radius),
                          normal_radii=[float(r) for r in normal_radii], max_distance=float(max_distance),
                          tfM=tfm, Cxx=np.zeros((12, 12)) if registration_cov is None else registration_cov,
                          refPointMov=np.zeros(3))
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        distance, unc, _cov = algo.run()
    seconds = time.perf_counter() - started
    distance = -np.asarray(distance, dtype=np.float64)  # M3C2-EP measures p1 - p2: flip to M3C2's p2 - p1
    lod = np.asarray(unc["lodetection"], dtype=np.float64)
    return PeerResult(distance=distance, lod=lod, changed=_changed(distance, lod), core_index=core_index,
                      seconds=seconds,
                      params={"cyl_radius": float(cyl_radius), "normal_radii": [float(r) for r in normal_radii],
                              "max_distance": float(max_distance), "sigma_range": float(sigma_range),
                              "sigma_scan": float(sigma_scan), "sigma_yaw": float(sigma_yaw),
                              "core_points": len(core_index)})
