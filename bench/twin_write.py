"""What writing a large point set into the twin costs (issue 36, thirteenth and fourteenth parts): one composite
item (a georeferenced scan with per-point covariances, scores, states and fusion reasons) written as the first
epoch the way the runner writes it (``composite_to_elements``), then an append that changes the states of a few of
its points, then the set read back, each step's peak RSS above what the process held before it (the composite;
``/proc/self/clear_refs`` resets the peak), its seconds and the epoch's files. Three cases side by side, each in a
child process of its own, medians of ``--repeats`` runs: parts of ``PART_ELEMENTS`` rows each made from the item as
the writer asks for it (now); the same parts from the item's element set made whole first (the thirteenth part);
and one part (what one prim cost before parts).

    .venv/bin/python bench/twin_write.py [--points 5000000] [--changed 1000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _status(key: str) -> int:
    """A /proc/self/status figure in MB."""
    text = Path("/proc/self/status").read_text()
    return int(text.split(f"{key}:")[1].split()[0]) // 1024


def _metered(step):
    """Run ``step()``; its seconds and peak RSS above the RSS before it, in MB."""
    before = _status("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")
    start = time.perf_counter()
    step()
    return time.perf_counter() - start, _status("VmHWM") - before


def scan_item(n: int, seed: int = 0):
    """A composite item: a georeferenced scan of ``n`` points with covariances, scores, states and fusion reasons."""
    from gdt_pipeline.types import CompositeItem, Dataset, GaussianUncertainty

    rng = np.random.default_rng(seed)
    cov = np.empty((n, 3, 3))
    cov[:] = np.eye(3) * 1e-6
    utm = np.array([500_000.0, 5_400_000.0, 100.0])
    ds = Dataset(name="scan", role="as-is", points=rng.normal(size=(n, 3)) + utm, uncertainty=GaussianUncertainty(cov))
    return CompositeItem(key="scan", dataset=ds, epoch="E0", state=rng.integers(0, 4, n).astype(np.uint8),
                         score=rng.random(n), source_epoch=np.ones(n, np.int32), visible=np.ones(n, bool),
                         reason=np.full(n, 2, np.uint8))


def _sets(item, made_whole: bool) -> list:
    """The item as the runner hands it to the writer, or its element set made whole first."""
    from gdt_pipeline.twin_elements import composite_to_elements
    from gdt_pipeline.types import Composite
    from twin_store import whole

    sets = composite_to_elements(Composite(items=(item,)))
    return [whole(s) for s in sets] if made_whole else list(sets)


def child(n: int, changed: int, part_elements: int, made_whole: bool) -> dict:
    """One case, in this process: write, append, read; the figures as a dict."""
    import dataclasses

    import twin_store.parts as parts
    from twin_store import TwinStore

    parts.PART_ELEMENTS = part_elements
    item = scan_item(n)
    with tempfile.TemporaryDirectory() as tmp:
        store = TwinStore.create(Path(tmp) / "twin")
        write_s, write_mb = _metered(lambda: store.write_epoch("E0", _sets(item, made_whole), {"epoch": "E0"}))
        state = np.array(item.state)
        state[:changed] = 2
        later = dataclasses.replace(item, state=state)
        append_s, append_mb = _metered(lambda: store.write_epoch("E1", _sets(later, made_whole), {"epoch": "E1"}))
        read_s, read_mb = _metered(lambda: store.read_epoch("E1"))
        files = {p.name: p.stat().st_size for p in (Path(tmp) / "twin" / "epochs").iterdir()}
    return {"write_s": write_s, "write_mb": write_mb, "append_s": append_s, "append_mb": append_mb,
            "read_s": read_s, "read_mb": read_mb, "files": len(files),
            "e1_layer_mb": files["E1.usdc"] / 2**20, "epochs_mb": sum(files.values()) / 2**20}


def main() -> None:
    """Both cases side by side, medians of the repeats."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=5_000_000)
    ap.add_argument("--changed", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--whole", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.points, args.changed, args.child, args.whole)))
        return
    import twin_store.parts as parts

    size = parts.PART_ELEMENTS
    cases = {f"parts of {size:,}, each made as written (now)": (size, False),
             f"parts of {size:,}, the set made whole first": (size, True),
             "one part (as one prim before parts)": (args.points, True)}
    runs: dict[str, list[dict]] = {name: [] for name in cases}
    for _ in range(args.repeats):
        for name, (rows, made_whole) in cases.items():  # interleaved, so that the machine's drift hits all alike
            out = subprocess.run([sys.executable, __file__, "--points", str(args.points), "--changed",
                                  str(args.changed), "--child", str(rows), *(["--whole"] if made_whole else [])],
                                 check=True, capture_output=True, text=True)
            runs[name].append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"{args.points:,} points, {args.changed:,} states changed in the append, medians of {args.repeats} runs")
    print("| case | write: s | write: peak MB | B/point | append: s | append: peak MB | E1 layer MB | read: s | "
          "read: peak MB | files | epochs MB |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, got in runs.items():
        med = {k: statistics.median(r[k] for r in got) for k in got[0]}
        print(f"| {name} | {med['write_s']:.1f} | {med['write_mb']:,.0f} | {med['write_mb'] * 2**20 / args.points:.0f}"
              f" | {med['append_s']:.1f} | {med['append_mb']:,.0f} | {med['e1_layer_mb']:.1f} | {med['read_s']:.1f} | "
              f"{med['read_mb']:,.0f} | {med['files']:.0f} | {med['epochs_mb']:.0f} |")


if __name__ == "__main__":
    main()
