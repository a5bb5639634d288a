"""Neighbourhood expectation on the ToF scene suite: per scene the default chain with ``auto``'s ``expectation:
point`` (the per-point test), the same chain with ``expectation: neighbourhood`` (what the default ``auto`` does
on these clouds), and the latter with the ``tof_low_cost`` preset
self-calibrated instead of the true profile; change F1 of each, the recall on thin added parts (≤ 5 cm across),
and the truth-tuned C2C and M3C2 on the per-point run's points. Scenes are seeded from SEED, which no test and no
parameter choice looked at.

    .venv/bin/python bench/expectation.py [--scenes 20] [--seed 9043] [--out out/bench/expectation]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import trimesh
from suite_bench import run_suite

from gdt_pipeline.evaluation.suite_scoring import score_scene
from gdt_pipeline.runner import run_workflow
from gdt_pipeline.simulation.suite import PROFILE_FILE, make_suite_scene

POOL = "  - uses: auto\n    role: as-is\n    with: {expectation: neighbourhood}\n"
PER_POINT = "  - uses: auto\n    role: as-is\n    with: {expectation: point}\n"
VARIANTS = {  # name: (profile params or None for the true profile, pooled)
    "per point, true profile": (None, False),
    "expectation, true profile": (None, True),
    "expectation, preset + self-calibration": ("profile: tof_low_cost, self_calibrate: true", True),
}
THIN = 0.05  # m: a part this thin or thinner across is a thin object


def _variant(workflow: Path, name: str, profile: str | None, pooled: bool) -> Path:
    """The scene's workflow with the variant's sensor_model and correspondence parameters (its own twin folder)."""
    slug = name.replace(" ", "_").replace(",", "").replace("+", "and")
    text = workflow.read_text(encoding="utf-8").replace("twin: twin", f"twin: twin_{slug}")
    if profile is not None:
        text = text.replace(f"profile: {PROFILE_FILE}", profile)
    text = text.replace("  - uses: auto\n    role: as-is\n", POOL if pooled else PER_POINT)
    path = workflow.with_name(f"workflow_{slug}.yaml")
    path.write_text(text, encoding="utf-8")
    return path


def thin_recall(root: Path, twin: Path) -> tuple[int, int]:
    """Changed points on thin added parts, and how many of them the twin marks new."""
    from gdt_pipeline.types import ChangeState
    from twin_store import TwinStore

    meta = json.loads((root / "scene.json").read_text())
    thin = {n for n, s in meta["objects"].items() if s == "new"
            and min(trimesh.load(root / f"truth_{n}.obj").bounding_box_oriented.primitive.extents) <= THIN}
    sets = {es.key: es for es in TwinStore.open(twin).read_epoch("E1")}
    hit = total = 0
    for k in range(len(meta["stations"])):
        t = np.load(root / f"scan_E1_s{k}_truth.npz")
        names = [str(n) for n in t["object_names"]]
        on = np.isin(np.array(names)[t["object_id"]], list(thin)) & t["changed"].astype(bool)
        new = sets[f"E1_scan_E1_s{k}"].state == ChangeState.NEW
        total += int(on.sum())
        hit += int((on & new).sum())
    return hit, total


def run_scene(root: Path, seed: int, registry: object) -> dict:
    """One scene: F1 per variant, the truth-tuned C2C, thin-part recall per variant."""
    scene = make_suite_scene("tof", root, seed)
    row: dict = {"seed": seed, "f1": {}, "seconds": {}, "thin": {}}
    for name, (profile, pooled) in VARIANTS.items():
        wf = _variant(scene.workflow, name, profile, pooled)
        t0 = time.perf_counter()
        twin = run_workflow(wf, registry=registry, overwrite=True).twin
        row["seconds"][name] = round(time.perf_counter() - t0, 2)
        peers = ("c2c", "m3c2") if name == "per point, true profile" else ()
        scored = score_scene(wf, twin, registry, peers, np.random.default_rng(seed), lambda msg: None)
        row["f1"][name] = (scored["methods"].get("gdt") or {}).get("f1")
        if peers:
            row["c2c_best"] = (scored["methods"].get("c2c_best") or {}).get("f1")
            row["m3c2_best"] = (scored["methods"].get("m3c2_best") or {}).get("f1")
        row["thin"][name] = thin_recall(root, twin)
    return row


def _line(row: dict) -> str:
    """One scene's progress line."""
    f1 = "  ".join(f"{n}: {v:.3f}" if v is not None else f"{n}: -" for n, v in row["f1"].items())
    return (f"{f1}  C2C best τ*: {row.get('c2c_best') or 0:.3f}  M3C2 best*: {row.get('m3c2_best') or 0:.3f}  "
            f"({sum(row['seconds'].values()):.0f} s)")


def print_summary(rows: list[dict]) -> None:
    """Mean and worst F1 and thin-part recall per variant."""
    for name in VARIANTS:
        f1 = np.array([r["f1"][name] for r in rows if r["f1"][name] is not None])
        hit = sum(r["thin"][name][0] for r in rows)
        total = sum(r["thin"][name][1] for r in rows)
        secs = np.median([r["seconds"][name] for r in rows])
        print(f"{name:40s} mean F1 {f1.mean():.4f}  worst {f1.min():.4f}  thin-part recall "
              f"{hit / total if total else float('nan'):.3f} ({total} points)  median run {secs:.1f} s  (n={len(f1)})")
    for key, label in (("c2c_best", "C2C, best τ on the truth*"), ("m3c2_best", "M3C2, best r and reg on the truth*")):
        peer = np.array([r[key] for r in rows if r.get(key) is not None])
        if len(peer):
            print(f"{label:40s} mean F1 {peer.mean():.4f}  worst {peer.min():.4f}")
    pooled = "expectation, true profile"
    above = sum(1 for r in rows if r["f1"][pooled] is not None and r.get("m3c2_best") is not None
                and r["f1"][pooled] > r["m3c2_best"])
    print(f"{pooled} above the best-tuned M3C2 on {above} of {len(rows)} scenes")


if __name__ == "__main__":
    sys.exit(run_suite(__doc__, 9043, "out/bench/expectation", run_scene, _line, print_summary))
