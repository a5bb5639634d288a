"""``gdt eval --suite``: generate N random scenes of a suite, run each scene's default workflow, score every twin
against the scene's truth with the peers on the same points, and summarise per method over the scenes (mean and
worst)."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import GdtError
from ..plugins import Registry, load_registry
from ..runner import run_workflow
from .suite_report import summarise
from .suite_scoring import score_scene

SUITE_PEERS = ("c2c", "m3c2")  # M3C2-EP runs at tens of core points per second: only when asked for


def scene_seed(seed: int, k: int) -> int:
    """The seed of scene ``k`` of a run with seed ``seed``: independent streams for every (seed, k)."""
    return int(np.random.SeedSequence([seed, k]).generate_state(1)[0])


def _fresh_dir(path: Path) -> None:
    """Empty a scene directory left by an earlier run (only one that holds a suite scene), so no file of another
    draw (a fifth station's scan) survives beside the new scene."""
    if not path.exists():
        return
    meta = path / "scene.json"
    written = json.loads(meta.read_text(encoding="utf-8")) if meta.is_file() else {}
    if "suite" not in written and "family" not in written:  # "family": written before the suites were renamed
        raise FileExistsError(f"{path} exists and is not a suite scene directory; choose another --out")
    shutil.rmtree(path)


def _line(k: int, n: int, row: dict[str, Any]) -> str:
    """The progress line of one scored scene."""
    def f(x: Any) -> str:
        return "–" if x is None else f"{x:.3f}"

    counts = {s: sum(v == s for v in row["objects"].values()) for s in ("new", "removed", "moved")}
    m = row["methods"]
    rem = (row.get("removal") or {}).get("methods", {}).get("gdt", {})
    peers = "; ".join(f"{name} F1 {f(m[name]['f1'])}" for name in ("c2c_best", "m3c2_best") if name in m)
    return (f"scene {k + 1}/{n} (seed {row['seed']}): {row['elements']:,} {'facets' if row['mesh'] else 'points'}, "
            f"{row['stations']} station(s), {'pose files' if row['pose_files'] else 'viewpoints only'}, "
            f"+{counts['new']} −{counts['removed']} ~{counts['moved']}: gdt F1 {f(m['gdt']['f1'])}, removal "
            f"{f(rem.get('recall'))}, false removals {f(rem.get('false_removals'))}" + (f"; {peers}" if peers else "")
            + f" ({row['seconds']['total']:.0f} s)")


def evaluate_scene(suite: str, k: int, seed: int, out: Path, registry: Registry, peers: tuple[str, ...],
                   say: Any) -> dict[str, Any]:
    """Generate scene ``k``, run its workflow and score it: its result row."""
    from ..simulation.suite import make_suite_scene

    s = scene_seed(seed, k)
    root = out / f"scene_{k:03d}"
    _fresh_dir(root)
    t0 = time.perf_counter()
    scene = make_suite_scene(suite, root, s)
    t1 = time.perf_counter()
    twin = run_workflow(scene.workflow, registry=registry, overwrite=True).twin
    t2 = time.perf_counter()
    row = score_scene(scene.workflow, twin, registry, peers, np.random.default_rng([seed, k, 1]), say)
    t3 = time.perf_counter()
    row.update(scene=k, seed=s, dir=str(root), mesh=scene.as_mesh, stations=len(scene.viewpoints),
               pose_files=scene.pose_files, points=scene.points, objects=scene.states,
               seconds={"generate": round(t1 - t0, 2), "run": round(t2 - t1, 2), "score": round(t3 - t2, 2),
                        "total": round(t3 - t0, 2)})
    return row


def evaluate_suite(suite: str, *, scenes: int, seed: int, out: str | Path, peers: tuple[str, ...] = SUITE_PEERS,
                    registry: Registry | None = None, progress: Any = None) -> dict[str, Any]:
    """Score ``scenes`` random scenes of ``suite`` (scene k seeded from (seed, k)): per scene and per method over
    the scenes (mean and worst change F1, removal recall by visible area, false removals by area)."""
    from ..simulation.suite import SUITES

    if suite not in SUITES:
        raise ValueError(f"unknown scene suite {suite!r}; choose from {', '.join(SUITES)}")
    if scenes < 1:
        raise ValueError("--scenes must be at least 1")
    say = progress or (lambda msg: None)
    registry = registry or load_registry()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    rows, failed = [], []
    for k in range(scenes):
        try:
            rows.append(evaluate_scene(suite, k, seed, out, registry, peers, say))
        except GdtError as exc:  # a scene the workflow refuses is a finding to report, not the end of the suite
            failed.append({"scene": k, "seed": scene_seed(seed, k), "error": str(exc)})
            say(f"scene {k + 1}/{scenes} (seed {scene_seed(seed, k)}): FAILED: {exc}")
            continue
        say(_line(k, scenes, rows[-1]))
    return {"suite": suite, "seed": seed, "scenes": scenes, "out": str(out), "peers": list(peers),
            "seconds": round(time.perf_counter() - started, 1), "summary": summarise(rows), "rows": rows,
            "failed": failed}
