"""The driver the ToF suite benches share: scene k of ``--scenes`` from ``scene_seed(--seed, k)`` into
``--out``/scene_<k>, a line per scene, a summary, and every row in ``results.json``."""

from __future__ import annotations

import argparse
import json
import shutil
from collections.abc import Callable
from pathlib import Path

from gdt_pipeline.evaluation.suite import scene_seed
from gdt_pipeline.plugins import load_registry


def run_suite(doc: str, seed: int, out: str, run_scene: Callable[[Path, int, object], dict],
               line: Callable[[dict], str], summary: Callable[[list[dict]], None]) -> None:
    """Parse the command line, run every scene with ``run_scene(root, seed, registry)``, print ``line(row)`` per
    scene and ``summary(rows)`` at the end."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=seed)
    ap.add_argument("--out", type=Path, default=Path(out))
    args = ap.parse_args()
    registry = load_registry()
    rows = []
    for k in range(args.scenes):
        root = args.out / f"scene_{k:03d}"
        shutil.rmtree(root, ignore_errors=True)
        row = run_scene(root, scene_seed(args.seed, k), registry)
        rows.append(row)
        print(f"scene {k:2d} seed {row['seed']}: {line(row)}", flush=True)
    summary(rows)
    (args.out / "results.json").write_text(json.dumps(rows, indent=2) + "\n")
