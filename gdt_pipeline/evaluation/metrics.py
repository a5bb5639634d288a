"""Scores of a change mask against the truth, and the threshold sweeps that give the peers' upper bounds."""

from __future__ import annotations

from typing import Any

import numpy as np


def prf(pred: np.ndarray, truth: np.ndarray) -> dict[str, Any]:
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


def score_key(m: dict[str, Any]) -> float:
    """What a sweep maximises: F1 where there is true change, else the fewest false alarms."""
    return m["f1"] if m["f1"] is not None else -(m["false_alarm_rate"] or 0.0)


def sweep(margin: np.ndarray, truth: np.ndarray, candidates: np.ndarray) -> tuple[float, dict[str, Any]]:
    """Best threshold t of the rule ``margin > t`` over the candidates, scored on the truth."""
    best = max(((float(t), prf(~(margin <= t), truth)) for t in candidates), key=lambda x: score_key(x[1]))
    return best


def threshold_candidates(values: np.ndarray) -> np.ndarray:
    """Thresholds spanning the finite values: log-spaced plus quantiles, so a rare change still gets a candidate."""
    v = values[np.isfinite(values) & (values > 0)]
    if not v.size:
        return np.array([0.0])
    logs = np.geomspace(max(v.min(), 1e-6), v.max(), 80)
    return np.unique(np.concatenate([logs, np.quantile(v, np.linspace(0.0, 1.0, 81))]))
