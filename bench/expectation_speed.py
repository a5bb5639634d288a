"""Speed of the neighbourhood expectation against py4dgeo's M3C2 on the same ToF clouds, side by side.

Per ToF suite scene (``--seed``, ``--scenes``) and run, each in a child process: ``gdt run`` of the scene's
chain with ``auto``'s ``expectation: point`` (the per-point test) and with ``expectation: neighbourhood``, wall seconds
(reading, every stage, writing the twin) and peak RSS; and py4dgeo's M3C2 with its documented default cylinder
(about 30 points, normals at twice that) on the same scan points against the CAD sampled at their spacing on the
facets facing a station (what ``gdt eval --suite`` gives it), its own seconds and peak RSS. Prints medians over
``--repeats`` runs, points/s, bytes per point and the ratio of gdt's points/s to M3C2's.

    .venv/bin/python bench/expectation_speed.py [--scenes 3] [--seed 9043] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from speed import GDT, ROOT, run_child

VARIANTS = {"per point": "    with: {expectation: point}\n", "expectation": "    with: {expectation: neighbourhood}\n"}


def _workflow(scene: Path, name: str, extra: str) -> Path:
    """The scene's workflow with the variant's ``auto`` parameters and twin folder."""
    text = (scene / "workflow.yaml").read_text(encoding="utf-8").replace("twin: twin", f"twin: twin_speed_{name[:3]}")
    text = text.replace("  - uses: auto\n    role: as-is\n", "  - uses: auto\n    role: as-is\n" + extra)
    path = scene / f"workflow_speed_{name[:3]}.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def m3c2_child(scene: Path) -> None:
    """(Child mode) py4dgeo M3C2 of the scene's E1 scans against its E0 CAD, as the suite evaluation runs it."""
    from gdt_pipeline.evaluation.peers import m3c2
    from gdt_pipeline.evaluation.twin_points import sample_sets
    from gdt_pipeline.plugins import load_registry
    from gdt_pipeline.runner import read_dataset
    from twin_store import TwinStore

    meta = json.loads((scene / "scene.json").read_text())
    points = np.concatenate([read_dataset(p, load_registry(), name="s", kind="points").points
                             for p in sorted(scene.glob("scan_E1_s[0-9].ply"))])
    extent = np.ptp(points, axis=0)
    spacing = np.sqrt(max(float(np.sort(extent)[1:].prod()), 1e-6) / len(points))
    cyl = float(np.sqrt(30.0 / np.pi) * spacing)
    eyes = np.array([s["eye"] for s in meta["stations"]])
    ref = sample_sets(TwinStore.open(scene / "twin_speed_per").read_epoch("E0"), spacing, np.random.default_rng(0),
                      facing=eyes)
    result = m3c2(ref, points, cyl_radius=cyl, normal_radii=(2 * cyl,), max_distance=max(0.5, 20 * cyl))
    print(json.dumps({"seconds": result.seconds, "points": len(points)}))


def main() -> None:
    """Run every scene's variants and M3C2 ``--repeats`` times; print medians and ratios."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--seed", type=int, default=9043)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "expectation_speed")
    ap.add_argument("--m3c2-child", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.m3c2_child:
        return m3c2_child(args.m3c2_child)
    from gdt_pipeline.evaluation.suite import scene_seed
    from gdt_pipeline.simulation.suite import make_suite_scene

    for k in range(args.scenes):
        scene = make_suite_scene("tof", args.out / f"scene_{k:03d}", scene_seed(args.seed, k))
        runs: dict[str, list[tuple[float, float]]] = {name: [] for name in (*VARIANTS, "M3C2")}
        for _ in range(args.repeats):
            for name, extra in VARIANTS.items():
                wall, rss, _ = run_child([*GDT, "run", _workflow(scene.root, name, extra).name, "--overwrite",
                                          "--quiet", "--no-report"], scene.root)
                runs[name].append((wall, rss))
            _, rss, out = run_child([sys.executable, __file__, "--m3c2-child", str(scene.root)], ROOT)
            runs["M3C2"].append((json.loads(out.strip().splitlines()[-1])["seconds"], rss))
        n = scene.points
        peer = n / float(np.median([s for s, _ in runs["M3C2"]]))
        print(f"scene {k} (seed {scene.seed}): {n:,} points")
        for name, values in runs.items():
            secs, rss = float(np.median([s for s, _ in values])), float(np.median([r for _, r in values]))
            print(f"  {name:12s} {secs:6.1f} s  {n / secs:9,.0f} points/s  peak {rss:6.0f} MB  "
                  f"{rss * 1e6 / n:6.0f} B/point  ratio to M3C2 {n / secs / peer:5.2f}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
