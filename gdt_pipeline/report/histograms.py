"""The report's histograms: per dataset of the epoch (the sets it brought in), the change scores with the threshold
the epoch cut them at, and the uncertainty σ; counted over every element in two lean passes (range, then counts),
so that only one set's values are ever held.

Where a threshold is recorded: ``fixed`` has τ in its params, ``tolerance_multiple`` reports ``tau`` (one per
recent dataset), ``calibrated_threshold`` reports ``calibration`` (τ per dataset, or one for the epoch's
datasets with ``per: epoch``), ``significance`` cuts p-values, not scores. A plugin's threshold is read alike when it
reports ``tau`` or has a ``tau`` param; otherwise the page says the threshold is not recorded.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from twin_store import LeanSet, TwinStore

from .scene import release_freed_memory
from .voxels import CHUNK

BINS = 60
LOG_DECADES = 1.0  # the x axis is logarithmic when the positive values span at least a decade
NOT_RECORDED = "threshold not recorded"


@dataclass(frozen=True)
class Histogram:
    """One dataset's counts over the group's shared bin edges."""

    key: str
    counts: np.ndarray
    values: int  # finite values counted
    off_axis: int  # finite values ≤ 0, not on a logarithmic axis
    threshold: float | None = None
    note: str = ""


@dataclass(frozen=True)
class HistogramGroup:
    """The histograms of one per-element value over the epoch's datasets, on shared edges."""

    field: str
    edges: np.ndarray
    log: bool
    histograms: list[Histogram]


def dataset_keys(provenance: dict[str, Any], epoch: str) -> list[str]:
    """The set keys of the epoch's recent datasets in the order the stages saw them (one per dataset a file gave)."""
    keys = []
    for inp in provenance.get("inputs", []):
        names = [d.get("name") for d in inp.get("datasets") or []] or [inp.get("name")]
        keys += [f"{epoch}_{name}" for name in names if name]
    return keys


def _per_query(entries: list[dict[str, Any]], n: int) -> dict[int, tuple[float, str]]:
    out = {}
    for c in entries:
        queries = c.get("query") if isinstance(c.get("query"), list) else [c.get("query")]
        note = (f"calibrated: false-alarm target {c.get('false_alarm_target')}, achieved "
                f"{c.get('false_alarm_achieved')} on {c.get('samples')} simulated unchanged pairs")
        for q in queries:
            if isinstance(q, int) and 0 <= q < n and c.get("tau") is not None:
                out[q] = (float(c["tau"]), note)
    return out


def _stage_thresholds(stage: dict[str, Any], n: int) -> dict[int, tuple[float | None, str]]:
    """τ per recent dataset index from one threshold stage's record."""
    params, report, uses = stage.get("params") or {}, stage.get("report") or {}, stage.get("uses", "?")
    if isinstance(report.get("calibration"), list):
        return dict(_per_query(report["calibration"], n))
    tau = report.get("tau", params.get("tau"))
    if isinstance(tau, list):
        return {i: (float(t), f"{uses}: τ per dataset") for i, t in enumerate(tau[:n]) if t is not None}
    if isinstance(tau, int | float):
        return dict.fromkeys(range(n), (float(tau), f"{uses}: τ = {tau:g}"))
    if uses == "significance":
        return dict.fromkeys(range(n), (None, f"significance: changed where p < α = {params.get('alpha')}; no "
                                              f"threshold on the score"))
    return {}


def thresholds(provenance: dict[str, Any], epoch: str, new_keys: Sequence[str]) -> dict[str, tuple[float | None,
                                                                                                 str]]:
    """Per dataset key of the epoch: τ (None where none applies to scores) and a note saying where it came from."""
    keys = dataset_keys(provenance, epoch)
    if not set(new_keys) <= set(keys):  # an older record without the datasets a file gave: the sets' own order
        keys = list(new_keys)
    found: dict[int, tuple[float | None, str]] = {}
    for stage in provenance.get("stages", []):
        if stage.get("family") == "threshold":
            found.update(_stage_thresholds(stage, len(keys)))  # a later threshold stage decides
    return {key: found.get(keys.index(key), (None, NOT_RECORDED)) for key in new_keys}


def _finite(es: LeanSet, field: str) -> Iterator[np.ndarray]:
    """A set's finite values of ``field``, a chunk at a time (so that a chunk's temporaries stay small)."""
    values = es.field(field)
    for start in range(0, len(values), CHUNK):
        part = values[start:start + CHUNK]
        yield part[np.isfinite(part)]


def _range(store: TwinStore, epoch: str, field: str) -> tuple[list[str], float, float, float]:
    """The epoch's new set keys and, over their finite values, the minimum, maximum and smallest positive value."""
    keys, lo, hi, pos = [], np.inf, -np.inf, np.inf
    for es in store.iter_sets(epoch):
        if not es.new_here:
            continue
        keys.append(es.key)
        for v in _finite(es, field):
            if v.size:
                lo, hi = min(lo, float(v.min())), max(hi, float(v.max()))
                positive = v[v > 0]
                pos = min(pos, float(positive.min())) if positive.size else pos
        release_freed_memory()
    return keys, lo, hi, pos


def edges_for(lo: float, hi: float, pos: float, bins: int = BINS) -> tuple[np.ndarray, bool]:
    """Shared bin edges over [lo, hi], logarithmic from ``pos`` when the values span ``LOG_DECADES`` or more."""
    if not np.isfinite(lo):
        return np.linspace(0.0, 1.0, bins + 1), False
    if np.isfinite(pos) and hi > pos and np.log10(hi / pos) >= LOG_DECADES:
        return np.geomspace(pos, hi, bins + 1), True
    if hi <= lo:
        pad = max(abs(lo) * 0.01, 1e-12)
        lo, hi = lo - pad, hi + pad
    return np.linspace(lo, hi, bins + 1), False


def epoch_histograms(store: TwinStore, epoch: str, field: str, provenance: dict[str, Any] | None = None
                     ) -> HistogramGroup:
    """The histograms of ``field`` (``score`` or ``uncertainty``) over the datasets the epoch brought in; for
    scores each with its threshold."""
    keys, lo, hi, pos = _range(store, epoch, field)
    edges, log = edges_for(lo, hi, pos)
    cuts = thresholds(provenance or {}, epoch, keys) if field == "score" else {}
    out = []
    for es in store.iter_sets(epoch):
        if not es.new_here:
            continue
        counts, values, off = np.zeros(len(edges) - 1, np.int64), 0, 0
        for v in _finite(es, field):
            values += v.size
            off += int(np.sum(v <= 0)) if log else 0
            counts += np.histogram(v[v > 0] if log else v, bins=edges)[0]
        release_freed_memory()
        tau, note = cuts.get(es.key, (None, ""))
        out.append(Histogram(es.key, counts, values, off, tau, note))
    return HistogramGroup(field, edges, log, out)
