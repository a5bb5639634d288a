"""Tiles on generated family scenes no test looks at: each tile's halo (largest and median over tiles, per tile run)
and the tiled twin against the whole run's, element by element (issue 36: halos follow the points that need them).

    .venv/bin/python bench/tile_halos.py [--suite tof] [--seeds 9301,9302] [--tile-elements 25000]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from gdt_pipeline.plugins import load_registry
from gdt_pipeline.runner import run_workflow
from gdt_pipeline.runner.plan import TilingOptions
from gdt_pipeline.simulation.suite import make_suite_scene
from twin_store import TwinStore


def _elements(twin: Path) -> dict:
    store = TwinStore.open(twin)
    return {(ep, es.key): es for ep in store.epochs() for es in store.read_epoch(ep)}


def _halos(twin: Path) -> list[str]:
    """Per epoch and tile run, its stages and its halos (largest and median over its tiles)."""
    store = TwinStore.open(twin)
    out = []
    for ep in store.epochs():
        for st in store.provenance(ep)["stages"]:
            tiling = st.get("report", {}).get("tiling")
            if tiling and tiling.get("halo", 0) > 0:
                out.append(f"{ep} {st['uses']}: {tiling['tiles']} tiles, halo largest {tiling['halo']:.3f}, "
                           f"median {tiling.get('halo_median', tiling['halo']):.3f}")
    return out


def _compare(a: dict, b: dict) -> str:
    states = elements = 0
    worst = 0.0
    for key, x in a.items():
        y = b[key]
        elements += len(x.state)
        states += int(np.sum(x.state != y.state))
        both = np.isfinite(x.score) & np.isfinite(y.score)
        if both.any():
            worst = max(worst, float(np.max(np.abs(x.score[both] - y.score[both]))))
    return f"{states} of {elements:,} element states differ, largest score difference {worst:.3g}"


def main() -> None:
    """Each seed's scene, whole and tiled."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--suite", default="tof")
    ap.add_argument("--seeds", default="9301,9302")
    ap.add_argument("--tile-elements", type=int, default=25_000)
    args = ap.parse_args()
    registry = load_registry()
    for seed in (int(s) for s in args.seeds.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            scene = make_suite_scene(args.suite, Path(tmp) / "scene", seed).workflow
            t0 = time.perf_counter()
            whole = run_workflow(scene, registry=registry, twin=Path(tmp) / "whole").twin
            t1 = time.perf_counter()
            tiled = run_workflow(scene, registry=registry, twin=Path(tmp) / "tiled",
                                 tiling=TilingOptions(max_elements=args.tile_elements)).twin
            t2 = time.perf_counter()
            print(f"{args.suite} seed {seed}: whole {t1 - t0:.1f} s, tiled {t2 - t1:.1f} s; "
                  f"{_compare(_elements(whole), _elements(tiled))}", flush=True)
            for line in _halos(tiled):
                print(f"  {line}", flush=True)


if __name__ == "__main__":
    main()
