"""Self-calibration on the ToF scene suite: per scene the default chain run three ways, with the scanner's true
profile, with the ``tof_low_cost`` preset as it is, and with the preset self-calibrated against the scene's CAD
(``sensor_model`` ``self_calibrate: true``); change F1 of each against the truth, and the fitted scale against the
true one. Scenes are seeded from SEED, which no test and no parameter choice looked at.

    .venv/bin/python bench/self_calibration.py [--scenes 20] [--seed 7717] [--out out/bench/self_calibration]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import yaml
from suite_bench import run_suite

from gdt_pipeline.evaluation.suite_scoring import score_scene
from gdt_pipeline.runner import run_workflow
from gdt_pipeline.simulation.suite import PROFILE_FILE, make_suite_scene

VARIANTS = {
    "true profile": None,
    "preset": "profile: tof_low_cost",
    "preset + self-calibration": "profile: tof_low_cost, self_calibrate: true",
}


def _variant(workflow: Path, name: str, params: str | None) -> Path:
    """The scene's workflow with the sensor_model's profile swapped (its own twin folder)."""
    text = workflow.read_text(encoding="utf-8")
    if params is not None:
        text = text.replace(f"profile: {PROFILE_FILE}", params)
    text = text.replace("twin: twin", f"twin: twin_{name.replace(' ', '_').replace('+', 'and')}")
    path = workflow.with_name(f"workflow_{name.replace(' ', '_').replace('+', 'and')}.yaml")
    path.write_text(text, encoding="utf-8")
    return path


def _fitted(twin: Path) -> dict | None:
    from twin_store import TwinStore

    for st in TwinStore.open(twin).provenance("E1")["stages"]:
        if st["uses"] == "sensor_model":
            return st["report"].get("self_calibration")
    return None


def run_scene(root: Path, seed: int, registry: object) -> dict:
    """One scene: F1 of gdt per variant, the true scale and the fitted one."""
    scene = make_suite_scene("tof", root, seed)
    true_scale = yaml.safe_load((root / PROFILE_FILE).read_text())["range_sigma"][0] / 0.002
    row: dict = {"seed": seed, "true_scale": true_scale, "f1": {}, "seconds": {}}
    for name, params in VARIANTS.items():
        wf = _variant(scene.workflow, name, params)
        t0 = time.perf_counter()
        twin = run_workflow(wf, registry=registry, overwrite=True).twin
        row["seconds"][name] = round(time.perf_counter() - t0, 2)
        scored = score_scene(wf, twin, registry, (), np.random.default_rng(seed), lambda msg: None)
        row["f1"][name] = (scored["methods"].get("gdt") or {}).get("f1")
        if params and "self_calibrate" in params:
            fit = _fitted(twin) or {}
            row["fitted_scale"], row["fit"] = fit.get("range_scale"), {k: fit.get(k) for k in (
                "points", "outlier_share", "bias", "normalized_rms", "em_rounds")}
    return row


def _line(row: dict) -> str:
    """One scene's progress line."""
    f1 = "  ".join(f"{n}: {v:.3f}" if v is not None else f"{n}: -" for n, v in row["f1"].items())
    return f"true ×{row['true_scale']:.3f} fitted ×{row['fitted_scale'] or 0:.3f}  {f1}"


def print_summary(rows: list[dict]) -> None:
    """Mean and worst F1 per variant; how often the fitted scale is within 20 % of the true one."""
    for name in VARIANTS:
        f1 = np.array([r["f1"][name] for r in rows if r["f1"][name] is not None])
        print(f"{name:28s} mean F1 {f1.mean():.4f}  worst {f1.min():.4f}  (n={len(f1)})")
    err = np.array([abs(r["fitted_scale"] / r["true_scale"] - 1) for r in rows if r.get("fitted_scale")])
    print(f"fitted scale within 20 % of the true one: {int((err <= 0.2).sum())} of {len(rows)} scenes "
          f"(median error {np.median(err):.1%}, worst {err.max():.1%})")


if __name__ == "__main__":
    sys.exit(run_suite(__doc__, 7717, "out/bench/self_calibration", run_scene, _line, print_summary))
