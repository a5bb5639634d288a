"""Speed of the whole detection against py4dgeo's M3C2 on the same clouds, measured side by side (issue 20).

The scene (``speed_scene``): the counter CAD part (83,750 facets, ±0.5 mm boxes) with a 5 × 5 × 3 cm block added,
scanned with structured light from four stations 0.6 m away, at each size asked for. Per size and run:

- gdt: ``gdt run`` of the default chain (``sensor_model``, ``sensor_frustum``, ``auto``, ``bhattacharyya``,
  ``calibrated_threshold``, ``most_reliable``) in a child process: wall seconds (reading, every stage, writing the
  twin), seconds per stage, peak RSS;
- M3C2: py4dgeo's M3C2 in a child process on the same scan points (every one a core point) against the CAD sampled at
  the scans' density, cylinder radius 2 mm, normals at 4 mm, both threads: its own seconds (epochs, KD-trees,
  normals, distances; reading the clouds not counted) and peak RSS.

Prints the medians over ``--repeats`` runs (the machine is shared and noisy), the ratio of gdt's points/s to M3C2's,
bytes per point, the Bhattacharyya stage's share of pairs per integration path and its largest error bound, and
gdt's F1 against the simulated truth.

    .venv/bin/python bench/speed.py [--sizes 1000000,5000000] [--repeats 3] [--out out/bench/speed]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from speed_scene import COUNTER, build

ROOT = Path(__file__).resolve().parents[1]
GDT = [sys.executable, "-m", "gdt_pipeline.cli"]


def run_child(cmd: list[str], cwd: Path) -> tuple[float, float, str]:
    """Wall seconds, peak RSS (MB) and stdout of one child process, measured with ``os.wait4``."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out = proc.stdout.read()
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise RuntimeError(f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n{err[-3000:]}")
    return wall, usage.ru_maxrss / 1024, out


def gdt_run(folder: Path) -> dict:
    """One ``gdt run`` of the scene's workflow: wall, peak RSS, seconds per stage, the Bhattacharyya report."""
    log = folder / "run.log.jsonl"
    log.unlink(missing_ok=True)
    wall, _, _ = run_child([*GDT, "run", "workflow.yaml", "--overwrite", "--quiet", "--log-file", str(log)], folder)
    stages: dict[str, float] = {}
    rss = 0.0
    for line in log.read_text().splitlines():
        event = json.loads(line)
        rss = max(rss, float(event.get("peak_rss_mb", 0.0)))
        if event.get("message") == "stage done" and event.get("epoch") == "E1":
            stages[event["stage"]] = stages.get(event["stage"], 0.0) + event["seconds"]
    # the child's own VmHWM, which the run logs after each stage: wait4's ru_maxrss carries the peak of this bench
    # process, which forked the child, across its exec (the scene generation is larger than a 1 M-point run)
    return {"wall": wall, "rss_mb": rss, "stages": stages, "bd": bhattacharyya_report(folder / "twin")}


def bhattacharyya_report(twin: Path) -> dict:
    """The Bhattacharyya stage's report in the E1 provenance of the twin (path shares, largest error bound)."""
    from twin_store import TwinStore

    prov = TwinStore.open(twin).provenance("E1")
    for stage in prov["stages"]:
        if stage["uses"] == "bhattacharyya":
            return stage.get("report") or {}
    return {}


def scan_spacing(clouds: list[np.ndarray], rng: np.random.Generator) -> float:
    """The scans' sampling spacing: 1/√density, the density of one scan from its 8 nearest neighbours (the merged
    cloud's nearest-neighbour distance would count the overlap of four stations and the noise as density)."""
    from scipy.spatial import cKDTree

    one = clouds[0]
    sub = one[rng.choice(len(one), min(20_000, len(one)), replace=False)]
    radius = float(np.median(cKDTree(one).query(sub, k=9, workers=-1)[0][:, 8]))
    return float(np.sqrt(np.pi * radius**2 / 8))


def m3c2_child(folder: Path) -> None:
    """(Child mode) py4dgeo M3C2 of the scene's scans against its CAD sampled at the scans' density; prints JSON.

    The cylinder reaches 1 cm each way: the part is 2.6 cm thick, and a longer one averages the top and the bottom
    face into a 6 mm offset everywhere."""
    import open3d as o3d
    import trimesh

    from gdt_pipeline import Dataset
    from gdt_pipeline.evaluation.peers import m3c2
    from gdt_pipeline.geometry import sample_surface
    from gdt_pipeline.memory import peak_rss_mb

    scans = sorted(folder.glob("scan_s[0-9].ply"))
    clouds = [np.asarray(o3d.io.read_point_cloud(str(p)).points) for p in scans]
    truth = np.concatenate([np.load(p.with_name(p.stem + "_truth.npz"))["changed"] for p in scans])
    query = np.concatenate(clouds)
    rng = np.random.default_rng(0)
    spacing = scan_spacing(clouds, rng)
    cad = trimesh.load(folder / "cad_part.stl", force="mesh")
    reference = sample_surface(Dataset("cad", "as-designed", np.asarray(cad.vertices), faces=np.asarray(cad.faces)),
                               spacing, rng)
    result = m3c2(reference, query, cyl_radius=0.002, normal_radii=(0.004,), max_distance=0.01)
    tp = int(np.sum(result.changed & truth))
    f1 = 2 * tp / max(1, int(result.changed.sum()) + int(truth.sum()))
    print(json.dumps({"seconds": result.seconds, "points": len(query), "reference": len(reference),
                      "spacing": spacing, "f1": f1, "peak_rss_mb": peak_rss_mb()}))


def m3c2_run(folder: Path) -> dict:
    """One M3C2 child: its own seconds, its own peak RSS (VmHWM, as for gdt) and what it reports."""
    _, _, out = run_child([sys.executable, __file__, "--m3c2-child", str(folder)], ROOT)
    report = json.loads(out.strip().splitlines()[-1])
    return {**report, "rss_mb": report.pop("peak_rss_mb")}


def f1_score(folder: Path) -> float:
    """gdt's F1 on the changed (block) points against the simulated truth, via ``gdt eval --twin``."""
    out_json = folder / "eval.json"
    run_child([*GDT, "eval", "workflow.yaml", "--twin", "twin", "--peers", "none", "--no-generate", "--json",
               str(out_json)], folder)
    result = json.loads(out_json.read_text())
    return float(_find(result, "f1"))


def _find(tree: object, key: str) -> object:
    """The first value stored under ``key`` anywhere in a JSON tree."""
    if isinstance(tree, dict):
        if key in tree:
            return tree[key]
        tree = list(tree.values())
    if isinstance(tree, list):
        for value in tree:
            found = _find(value, key)
            if found is not None:
                return found
    return None


def report(n: int, gdt: list[dict], peer: list[dict], f1: float) -> None:
    """Print one size's medians."""
    wall = float(np.median([r["wall"] for r in gdt]))
    rss = float(np.median([r["rss_mb"] for r in gdt]))
    m_sec = float(np.median([r["seconds"] for r in peer]))
    m_rss = float(np.median([r["rss_mb"] for r in peer]))
    print(f"\n== {n:,} points, medians of {len(gdt)} runs ==")
    for stage in gdt[0]["stages"]:
        print(f"  {stage:<22} {np.median([r['stages'].get(stage, 0.0) for r in gdt]):8.2f} s")
    print(f"  {'gdt, whole run':<22} {wall:8.2f} s  {n / wall:>10,.0f} points/s  peak {rss:7.0f} MB  "
          f"{rss * 2**20 / n:6.0f} B/point")
    print(f"  {'py4dgeo M3C2':<22} {m_sec:8.2f} s  {n / m_sec:>10,.0f} points/s  peak {m_rss:7.0f} MB  "
          f"{m_rss * 2**20 / n:6.0f} B/point")
    print(f"  M3C2 reference: {peer[0]['reference']:,} CAD samples at {peer[0]['spacing'] * 1e3:.2f} mm; "
          f"M3C2 F1 on the block: {peer[0]['f1']:.4f}")
    print(f"  ratio gdt / M3C2 points/s: {m_sec / wall:.2f}   gdt F1 on the block: {f1:.4f}")
    bd = gdt[0]["bd"]
    if bd:
        shares = ", ".join(f"{k} {v:.4%}" for k, v in (bd.get("path_shares") or {}).items())
        print(f"  Bhattacharyya paths: {shares or 'n/a'}; largest BC error bound {bd.get('max_integration_error')}"
              f" (ε_T {bd.get('tolerance')})")


def main() -> None:
    """Build each size's scene, run gdt and M3C2 in turn, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="1000000,5000000")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "speed")
    ap.add_argument("--cad", type=Path, default=COUNTER, help="The counter part (default: ../shared/data beside the "
                    "repository); when absent, a generated plate stands in.")
    ap.add_argument("--m3c2-child", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.m3c2_child:
        m3c2_child(args.m3c2_child)
        return
    warmed = False
    for size in (int(s) for s in args.sizes.split(",")):
        scene = build(args.out / f"{size}", size, counter=args.cad)
        print(f"scene: {scene['source']}, {scene['facets']:,} facets, {scene['points']:,} points", flush=True)
        gdt, peer = [], []
        if not warmed:  # numba compiles the kernels once per installation (cached beside them): not counted
            gdt_run(scene["workflow"].parent)
            warmed = True
        for _ in range(args.repeats):  # alternate, so that both meet the same load on a shared machine
            gdt.append(gdt_run(scene["workflow"].parent))
            peer.append(m3c2_run(scene["workflow"].parent))
        report(scene["points"], gdt, peer, f1_score(scene["workflow"].parent))


if __name__ == "__main__":
    main()
