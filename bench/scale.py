"""Scale: the default chain on 1 M, 10 M and 50 M simulated points, whole and tiled on each executor (issue 21).

The scene is the speed benchmark's (``speed_scene``: the counter CAD part with a block added, four structured-light
stations). Per size and way of running, ``gdt run`` in a child process, after one untimed tiled warm-up run on a
200 k-point scene that compiles the kernels; printed: wall seconds, points/s, the peak of the summed RSS of the
whole process tree (the run, its pool or Dask workers and scheduler; sampled every 0.2 s), bytes per point of the
tree and of the main process alone (its VmHWM, from the run's log), the tiles and the seconds per stage.

    .venv/bin/python bench/scale.py [--sizes 1000000,10000000,50000000] [--ways whole,serial,processes,dask]
        [--tile-elements 500000] [--workers 2] [--repeats 1]

A way that fails (out of memory) is printed as such with the peak it reached, and the next one runs; a way whose
bytes a point at the last size project past the free memory at this size is skipped, with the projection.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent))
from speed_scene import COUNTER, build

ROOT = Path(__file__).resolve().parents[1]
GDT = [sys.executable, "-m", "gdt_pipeline.cli"]
SAMPLE_SECONDS = 0.2
# A way is not tried at a size where the bytes a point it took at the last size would fill more than this share of
# the memory free now.
MEMORY_SHARE = 0.9
# The warm-up scene: big enough that every kernel runs on real tiles, small enough to take seconds.
WARM_UP_POINTS = 200_000


def tree_rss(proc: psutil.Process) -> int:
    """Summed RSS in bytes of a process and all its descendants (those that vanish mid-count are skipped)."""
    total = 0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            continue
    return total


def run_metered(cmd: list[str], cwd: Path) -> dict:
    """Wall seconds, peak process-tree RSS (MB), exit code and stderr tail of one child run."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    peak = [0]
    watched = psutil.Process(proc.pid)

    def sample() -> None:
        while proc.poll() is None:
            try:
                peak[0] = max(peak[0], tree_rss(watched))
            except psutil.Error:
                break
            time.sleep(SAMPLE_SECONDS)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    err = proc.stderr.read()
    proc.wait()
    sampler.join()
    return {"wall": time.perf_counter() - t0, "rss_mb": peak[0] / 2**20, "code": proc.returncode,
            "error": err[-600:]}


def way_args(way: str, tile_elements: int, workers: int) -> list[str]:
    """The ``gdt run`` options of one way of running."""
    if way == "whole":
        return []
    return ["--tile-elements", str(tile_elements), "--executor", way, "--workers", str(workers)]


def stage_seconds(log: Path) -> dict[str, float]:
    """Seconds per stage of epoch E1 from a run's JSON-lines log."""
    out: dict[str, float] = {}
    for line in log.read_text().splitlines() if log.exists() else []:
        event = json.loads(line)
        if event.get("message") == "stage done" and event.get("epoch") == "E1":
            out[event["stage"]] = out.get(event["stage"], 0.0) + event["seconds"]
    return out


def main_peak_mb(log: Path) -> float | None:
    """The peak RSS (MB) of the process that ran ``gdt run`` itself, workers not counted: the largest VmHWM its
    stage and epoch-written records logged."""
    peaks = [json.loads(line).get("peak_rss_mb") for line in log.read_text().splitlines()] if log.exists() else []
    peaks = [p for p in peaks if p is not None]
    return max(peaks) if peaks else None


def tiles_of(twin: Path) -> int | None:
    """How many tiles the E1 correspondence stage ran in (None for a whole run)."""
    from twin_store import TwinStore

    try:
        stages = TwinStore.open(twin).provenance("E1")["stages"]
    except Exception:
        return None
    tiled = [s["report"].get("tiling") for s in stages if isinstance(s.get("report"), dict)]
    return next((t["tiles"] for t in tiled if t), None)


def run_way(folder: Path, way: str, args: argparse.Namespace) -> dict:
    """One run of the scene's workflow one way; its figures."""
    log = folder / f"run-{way}.jsonl"
    log.unlink(missing_ok=True)
    cmd = [*GDT, "run", "workflow.yaml", "--overwrite", "--quiet", "--twin", f"twin-{way}", "--log-file", str(log),
           *way_args(way, args.tile_elements, args.workers)]
    res = run_metered(cmd, folder)
    res["stages"] = stage_seconds(log)
    res["main_mb"] = main_peak_mb(log)
    res["tiles"] = tiles_of(folder / f"twin-{way}") if res["code"] == 0 else None
    return res


def print_way(n: int, way: str, runs: list[dict]) -> None:
    """One line per way: medians of its runs."""
    ok = [r for r in runs if r["code"] == 0]
    if not ok:
        r = runs[0]
        print(f"  {way:<10} FAILED (exit {r['code']}) after {r['wall']:.0f} s at peak {r['rss_mb']:.0f} MB: "
              f"{r['error'].strip().splitlines()[-1] if r['error'].strip() else ''}", flush=True)
        return
    wall = float(np.median([r["wall"] for r in ok]))
    rss = float(np.median([r["rss_mb"] for r in ok]))
    stages = ", ".join(f"{k} {np.median([r['stages'].get(k, 0.0) for r in ok]):.1f}" for k in ok[0]["stages"])
    mains = [r["main_mb"] for r in ok if r.get("main_mb") is not None]
    main = f"  main process {np.median(mains) * 2**20 / n:5.0f} B/point" if mains else ""
    print(f"  {way:<10} {wall:8.1f} s {n / wall:>10,.0f} points/s  peak {rss:7.0f} MB  {rss * 2**20 / n:6.0f} B/point"
          f"{main}  tiles {ok[0]['tiles'] or '-'}   [{stages}]", flush=True)


def compare(folder: Path, way: str) -> str:
    """Element by element, the twin of ``way`` against the whole run's: states, visibility, scores."""
    from twin_store import TwinStore

    a, b = TwinStore.open(folder / "twin-whole"), TwinStore.open(folder / f"twin-{way}")
    states = visible = elements = 0
    worst = 0.0
    for epoch in a.epochs():
        theirs = {es.key: es for es in b.read_epoch(epoch)}
        for x in a.read_epoch(epoch):
            y = theirs[x.key]
            elements += len(x.state)
            states += int(np.sum(x.state != y.state))
            visible += int(np.sum(x.visible != y.visible))
            both = np.isfinite(x.score) & np.isfinite(y.score)
            if both.any():
                worst = max(worst, float(np.max(np.abs(x.score[both] - y.score[both]))))
    return (f"vs whole: {states} of {elements:,} element states differ, {visible} visibilities, largest score "
            f"difference {worst:.3g}")


def warm_up(args: argparse.Namespace) -> None:
    """One untimed tiled run on a small scene of the same kind: it compiles the kernels (cached on disk), which a
    full run of the first size did at the cost of that run's wall time."""
    scene = build(args.out / "warm-up", WARM_UP_POINTS, counter=args.cad)
    small = argparse.Namespace(tile_elements=WARM_UP_POINTS // 4, workers=args.workers)
    res = run_way(scene["workflow"].parent, "serial", small)
    if res["code"] != 0:
        raise SystemExit(f"the warm-up run failed (exit {res['code']}): {res['error'].strip()}")


def main() -> None:
    """Build each size's scene and run it every way asked, printing as it goes."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="1000000,10000000,50000000")
    ap.add_argument("--ways", default="whole,serial,processes,dask")
    ap.add_argument("--tile-elements", type=int, default=500_000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "scale")
    ap.add_argument("--cad", type=Path, default=COUNTER)
    args = ap.parse_args()
    warm_up(args)
    per_point: dict[str, float] = {}
    for size in (int(s) for s in args.sizes.split(",")):
        t0 = time.perf_counter()
        scene = build(args.out / f"{size}", size, counter=args.cad)
        folder = scene["workflow"].parent
        print(f"\n== {scene['points']:,} points ({scene['source']}; scene built in {time.perf_counter() - t0:.0f} s),"
              f" tiles of at most {args.tile_elements:,} elements, {args.workers} workers ==", flush=True)
        ways = [w for w in args.ways.split(",") if fits(w, per_point, scene["points"])]
        runs: dict[str, list[dict]] = {w: [] for w in ways}
        for _ in range(args.repeats):  # interleaved, so that a noisy spell on the shared machine hits every way
            for way in ways:
                runs[way].append(run_way(folder, way, args))
        for way in ways:
            ok = [r for r in runs[way] if r["code"] == 0]
            if ok:
                per_point[way] = float(np.median([r["rss_mb"] for r in ok])) * 2**20 / scene["points"]
            print_way(scene["points"], way, runs[way])
            if way != "whole" and runs[way][0]["code"] == 0 and (folder / "twin-whole").exists():
                print(f"  {'':<10} {compare(folder, way)}", flush=True)
                if "whole" in runs:
                    print(f"  {'':<10} {wall_ratio(runs[way], runs['whole'])}", flush=True)


def fits(way: str, per_point: dict[str, float], points: int) -> bool:
    """Whether a way's bytes a point at the last size leave room at this one (an out-of-memory kill on a shared
    machine takes others down too); printed when not."""
    need = per_point.get(way, 0.0) * points
    free = psutil.virtual_memory().available
    if need <= MEMORY_SHARE * free:
        return True
    print(f"  {way:<10} skipped: {per_point[way]:.0f} B/point measured at the last size would need "
          f"{need / 2**30:.1f} GB, {free / 2**30:.1f} GB are free", flush=True)
    return False


def wall_ratio(runs: list[dict], whole: list[dict]) -> str:
    """A way's wall time against the whole run's, measured in the same bench run: the ratio of the medians, and
    repeat by repeat (each pair ran one after the other)."""
    ok = [(r["wall"], w["wall"]) for r, w in zip(runs, whole, strict=False) if r["code"] == 0 and w["code"] == 0]
    if not ok:
        return "vs whole wall: no pair of runs to compare"
    ratio = np.median([r for r, _ in ok]) / np.median([w for _, w in ok])
    each = ", ".join(f"{r / w:.3f}" for r, w in ok)
    return f"vs whole wall: {ratio:.3f} ratio of medians (per repeat {each})"

if __name__ == "__main__":
    main()
