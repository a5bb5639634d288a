"""Change-detection F1 on the demo test scene: uncertainty-directed point-to-mesh correspondences against plain
closest-point ones, with per-point sensor-model covariances (the scan split per station, each with its viewpoint).

Run: .venv/bin/python bench/correspondence_eval.py   (under a minute)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import open3d as o3d

from gdt_pipeline.runner import run_workflow
from gdt_pipeline.simulation import make_test_scene
from twin_store import TwinStore

WORKFLOW = """\
name: correspondence-eval
twin: twin_{corr}_{thr}
seed: 1
epochs:
  - id: E0
    role: as-designed
    inputs:
      - {{path: data/cad_small_cuboid.obj}}
      - {{path: data/cad_frustum_a.obj}}
      - {{path: data/cad_frustum_b.obj}}
  - id: E1
    role: as-is
    inputs:
{inputs}
stages:
  - {{uses: constant, role: as-designed, with: {{model: box, half_widths: [0.002, 0.002, 0.002]}}}}
  - {{uses: sensor_model, role: as-is, with: {{profile: profile.yaml, incidence: false}}}}
  - {{uses: {corr}, role: as-is{corr_with}}}
  - {{uses: bhattacharyya, role: as-is}}
  - {{uses: {thr}, role: as-is, with: {thr_with}}}
  - uses: keep_unchanged
"""

PROFILE = """\
name: demo_tof_truth
units: m
range_sigma: [0.004, 0.0, 0.0]
lateral_sigma: [0.0013333333, 0.0]
min_cos_incidence: 0.2
"""


def main() -> int:
    """Run both correspondence methods with two thresholds and print F1 against the ground truth."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        files = make_test_scene(root / "data", seed=0)
        truth = np.load(files.truth["E1"])
        pts = np.asarray(o3d.io.read_point_cloud(str(files.scans["E1"])).points)
        inputs, order = [], []
        for k, vp in enumerate(files.viewpoints["E1"]):
            sel = np.flatnonzero(truth["viewpoint"] == k)
            order.append(sel)
            o3d.io.write_point_cloud(str(root / "data" / f"station{k}.ply"),
                                     o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[sel])))
            inputs.append(f"      - {{path: data/station{k}.ply, viewpoints: [{vp}]}}")
        changed = np.concatenate([truth["changed"][s] for s in order])
        (root / "profile.yaml").write_text(PROFILE)
        for corr, corr_with in (("nearest", ", with: {max_distance: 0.25}"), ("point_to_mesh", "")):
            for thr, thr_with in (("fixed", "{tau: 4.0}"), ("calibrated_threshold", "{false_alarm: 0.01}")):
                wf = root / f"{corr}_{thr}.yaml"
                wf.write_text(WORKFLOW.format(corr=corr, thr=thr, corr_with=corr_with, thr_with=thr_with,
                                              inputs="\n".join(inputs)))
                twin = run_workflow(wf).twin
                sets = {e.key: e for e in TwinStore.open(twin).read_epoch("E1")}
                state = np.concatenate([sets[f"E1_station{k}"].state for k in range(len(order))])
                pred = state == 1
                tp = np.sum(pred & changed)
                rows.append((corr, thr, tp / max(pred.sum(), 1), tp / changed.sum(),
                             2 * tp / (pred.sum() + changed.sum()), int(np.sum(pred & ~changed))))
    print("| correspondence | threshold | precision | recall | F1 | false alarms |")
    print("| --- | --- | --- | --- | --- | --- |")
    for corr, thr, p, r, f, fa in rows:
        print(f"| {corr} | {thr} | {p:.4f} | {r:.4f} | {f:.4f} | {fa} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
