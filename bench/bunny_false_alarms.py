"""False alarms of a bunny twin (workflows/real/bunny.yaml): per scan, the share flagged among the points that got a
score and among every decided point (scored, or new for want of a correspondence), where the points without a
correspondence (NaN score) lie, and how many are not comparable (no mesh surface at their place).

    .venv/bin/gdt run workflows/real/bunny.yaml --twin /tmp/bunny --no-report --overwrite
    .venv/bin/python bench/bunny_false_alarms.py /tmp/bunny
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

NEW, NOT_COMPARABLE = 1, 4  # gdt_pipeline.types.states.ChangeState


def scan_figures(points: np.ndarray, score: np.ndarray, state: np.ndarray) -> dict[str, Any]:
    """Flagged share among scored points, the unscored count and how many of them lie on the scan's sparse border."""
    scored = np.isfinite(score)
    # the sparsest tenth of the points (largest distance to the 8th neighbour): the range image's borders
    spacing = cKDTree(points).query(points, k=9)[0][:, -1]
    border = spacing >= np.quantile(spacing, 0.9)
    unscored = ~scored
    return {"points": len(score), "scored": int(scored.sum()), "flagged": int(np.sum(scored & (state == NEW))),
            "unscored": int(unscored.sum()), "decided": int(np.sum(state != NOT_COMPARABLE)),
            "flagged_decided": int(np.sum(state == NEW)), "not_comparable": int(np.sum(state == NOT_COMPARABLE)),
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
    head = ("scan", "points", "scored", "flagged", "share", "unscored", "on border", "decided", "flagged",
            "share", "not comp.")
    print(f"{head[0]:10s} " + " ".join(f"{h:>9s}" for h in head[1:]))
    for name, r in [*rows.items(), ("all", total)]:
        print(f"{name:10s} {r['points']:9d} {r['scored']:9d} {r['flagged']:9d} {r['flagged'] / r['scored']:9.2%} "
              f"{r['unscored']:9d} {r['unscored_on_border'] / max(r['unscored'], 1):9.1%} {r['decided']:9d} "
              f"{r['flagged_decided']:9d} {r['flagged_decided'] / max(r['decided'], 1):9.2%} "
              f"{r['not_comparable']:9d}")


if __name__ == "__main__":
    main()
