"""`gdt report` on twins too large for one page (issue 24): file size, seconds and peak RSS of the report process.

The twins come from the speed benchmark's scene (``speed_scene``: the counter CAD part with a block added, four
structured-light stations) at ``--points`` points, built once in ``out/bench/report/<points>`` and reused after
that. At the default 9 M each scan has 2.25 M points, more than the twin store's 2 M-point payload limit, so every
scan is a payload set with a decimated preview. Two twins: ``twin``, the default chain (CAD, then the scans: the
composite shows the CAD and what changed, the unchanged scan points being hidden), and ``twin_scans``, the scans
alone as the first epoch (every point shown). Then ``gdt report`` runs in a child process per twin and budget; its
peak RSS is its own ``ru_maxrss`` (``os.wait4``), measured by ``tests/child_meter.py``, a small interpreter that
starts it (Linux carries a process's peak across ``exec``: forked from this one, it would report this one's).

    .venv/bin/python bench/report.py [--points 9000000] [--budgets 500000,2000000] [--twin DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from speed_scene import COUNTER, build

ROOT = Path(__file__).resolve().parents[1]
GDT = [sys.executable, "-m", "gdt_pipeline.cli"]
METER = ROOT / "tests" / "child_meter.py"  # runs a command and writes its own peak RSS
LIMIT_MB, FILE_LIMIT_MB = 200, 30  # the bounds at the default budget


SCANS_ONLY = """\
name: report-bench-scans
description: the speed scene's scans alone, as the first epoch (every point is in the composite)
twin: twin_scans
seed: 7
units: m
epochs:
  - id: E0
    role: as-is
    inputs: {inputs}
stages:
  - uses: sensor_model
    with: {{profile: structured_light}}
  - uses: keep_unchanged
"""


def _run(folder: Path, workflow: str) -> None:
    t0 = time.perf_counter()
    subprocess.run([*GDT, "run", workflow, "--overwrite", "--quiet"], cwd=folder, check=True,
                   stdout=subprocess.DEVNULL)
    print(f"gdt run {workflow}: {time.perf_counter() - t0:.0f} s", flush=True)


def twins_for(points: int, out: Path) -> list[Path]:
    """The benchmark twins of about ``points`` points: built (scene, then ``gdt run``) unless they exist."""
    import yaml

    folder = out / str(points)
    if not (folder / "workflow.yaml").is_file():
        t0 = time.perf_counter()
        scene = build(folder, points, counter=COUNTER)
        print(f"scene: {scene['points']:,} points ({scene['source']}) in {time.perf_counter() - t0:.0f} s", flush=True)
    if not (folder / "twin" / "twin.usda").is_file():
        _run(folder, "workflow.yaml")
    if not (folder / "twin_scans" / "twin.usda").is_file():
        scans = yaml.safe_load((folder / "workflow.yaml").read_text())["epochs"][1]["inputs"]
        (folder / "scans.yaml").write_text(SCANS_ONLY.format(inputs=json.dumps(scans)))
        _run(folder, "scans.yaml")
    return [folder / "twin", folder / "twin_scans"]


def metered(cmd: list[str]) -> tuple[float, float, str]:
    """Wall seconds, peak RSS (MB) of the command itself, and its output."""
    with tempfile.TemporaryDirectory() as tmp:
        result, log = Path(tmp) / "result.json", Path(tmp) / "out.txt"
        with open(log, "w") as fh:
            subprocess.run([sys.executable, str(METER), str(result), "600", "8192", *cmd], stdout=fh,
                           stderr=subprocess.STDOUT, check=True)
        data, out = json.loads(result.read_text()), log.read_text().strip()
    if data["returncode"]:
        raise SystemExit(f"{' '.join(cmd)} failed ({data['returncode']}):\n{out}")
    return data["seconds"], data["peak_mb"], out


def main() -> None:
    """Build or reuse the twins, then time and meter one report per twin and budget."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=9_000_000)
    ap.add_argument("--budgets", default="500000,2000000")
    ap.add_argument("--twin", type=Path, help="Report on this twin instead of building the benchmark's.")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "report")
    args = ap.parse_args()
    from twin_store import TwinStore

    for twin in [args.twin] if args.twin else twins_for(args.points, args.out):
        store = TwinStore.open(twin)
        epoch = store.epochs()[-1]
        total = sum(len(es.field("state")) for es in store.iter_sets(epoch))
        print(f"\n== gdt report on {twin} at {epoch}: {total:,} elements ==", flush=True)
        for budget in (int(b) for b in args.budgets.split(",")):
            html = args.out / f"{twin.name}_report_{budget}.html"
            seconds, rss, out = metered([*GDT, "report", str(twin), "--budget", str(budget), "-o", str(html)])
            size = html.stat().st_size / 1e6
            verdict = "" if budget != 500_000 else (
                f"  [{'within' if rss <= LIMIT_MB and size <= FILE_LIMIT_MB else 'OVER'} the {LIMIT_MB} MB RSS / "
                f"{FILE_LIMIT_MB} MB file bounds]")
            print(f"  budget {budget:>9,}: {size:6.1f} MB file, {seconds:6.1f} s, peak RSS {rss:6.0f} MB{verdict}",
                  flush=True)
            print(f"    {out.splitlines()[-1] if out else ''}", flush=True)


if __name__ == "__main__":
    main()
