"""False alarms of a bunny twin (workflows/real/bunny.yaml): per scan, the share flagged among the points that got a
score, and where the points without a correspondence (NaN score) lie.

    .venv/bin/gdt run workflows/real/bunny.yaml --twin /tmp/bunny --no-report --overwrite
    .venv/bin/python bench/bunny_false_alarms.py /tmp/bunny
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

NEW = 1  # gdt_pipeline.types.states.ChangeState.NEW


def scan_figures(points: np.ndarray, score: np.ndarray, state: np.ndarray) -> dict[str, Any]:
    """Flagged share among scored points, the unscored count and how many of them lie on the scan's sparse border."""
    scored = np.isfinite(score)
    # the sparsest tenth of the points (largest distance to the 8th neighbour): the range image's borders
    spacing = cKDTree(points).query(points, k=9)[0][:, -1]
    border = spacing >= np.quantile(spacing, 0.9)
    unscored = ~scored
    return {"points": len(score), "scored": int(scored.sum()), "flagged": int(np.sum(scored & (state == NEW))),
            "unscored": int(unscored.sum()),
            "unscored_on_border": int(np.sum(unscored & border))}


def twin_figures(twin: Path, epoch: str = "E1") -> dict[str, dict[str, Any]]:
    """Per point set of ``epoch`` in the twin at ``twin``: its figures."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(twin / "twin.usda"))
    out = {}
    for prim in stage.Traverse():
        name = prim.GetName()
        if not name.startswith(f"{epoch}_") or not prim.IsA(UsdGeom.Points):
            continue
        pts = np.asarray(UsdGeom.Points(prim).GetPointsAttr().Get(), dtype=np.float64)
        score = np.asarray(prim.GetAttribute("primvars:gdt:changeScore").Get(), dtype=np.float64)
        state = np.asarray(prim.GetAttribute("primvars:gdt:changeState").Get(), dtype=np.int64)
        out[name[len(epoch) + 1:]] = scan_figures(pts, score, state)
    return out


def main() -> None:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("twin", type=Path)
    args = ap.parse_args()
    rows = twin_figures(args.twin)
    total = {k: sum(r[k] for r in rows.values()) for k in next(iter(rows.values()))}
    head = ("scan", "points", "scored", "flagged", "share", "unscored", "on border")
    print(f"{head[0]:10s} " + " ".join(f"{h:>7s}" for h in head[1:]))
    for name, r in [*rows.items(), ("all", total)]:
        print(f"{name:10s} {r['points']:7d} {r['scored']:7d} {r['flagged']:7d} {r['flagged'] / r['scored']:7.2%} "
              f"{r['unscored']:8d} {r['unscored_on_border'] / max(r['unscored'], 1):9.1%}")


if __name__ == "__main__":
    main()
