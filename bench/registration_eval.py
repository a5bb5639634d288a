"""Change-detection F1 on the demo test scene when the scan carries a registration error, with and without a
registrar, next to perfect alignment. Writes nothing outside a temporary folder; prints a markdown table.

Run: .venv/bin/python bench/registration_eval.py   (about half a minute)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from gdt_pipeline.runner import run_workflow
from gdt_pipeline.simulation import make_test_scene
from twin_store import TwinStore

REPO = Path(__file__).resolve().parents[1]
ERROR = np.eye(4)
ERROR[:3, :3] = Rotation.from_euler("xyz", [0.8, -1.2, 2.0], degrees=True).as_matrix()
ERROR[:3, 3] = [0.03, -0.02, 0.015]

REGISTRARS = {
    "perfect alignment (no error, identity)": ("identity", None, False),
    "registration error, identity": ("identity", None, True),
    "registration error, gicp": ("gicp", None, True),
    "registration error, point_to_plane": ("point_to_plane", None, True),
    "registration error, stable_areas": ("stable_areas", None, True),
}


def main() -> int:
    """Run every variant and print F1 against the ground truth."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        files = make_test_scene(root / "data" / "test_scene", seed=0)
        truth = np.load(files.truth["E1"])["changed"]
        pcd = o3d.io.read_point_cloud(str(files.scans["E1"]))
        moved = pcd.transform(ERROR)
        o3d.io.write_point_cloud(str(root / "data" / "test_scene" / "scan_E1_moved.ply"), moved)
        base = (REPO / "workflows" / "demo.yaml").read_text()
        for label, (registrar, _, with_error) in REGISTRARS.items():
            text = base.replace("  - uses: identity\n    role: as-is\n", f"  - uses: {registrar}\n    role: as-is\n")
            if with_error:
                text = text.replace("scan_E1.ply", "scan_E1_moved.ply")
            wf = root / f"{registrar}_{with_error}.yaml"
            wf.write_text(text)
            twin = run_workflow(wf, twin=root / f"twin_{registrar}_{with_error}").twin
            scan = next(e for e in TwinStore.open(twin).read_epoch("E1") if e.key == "E1_tof_scan")
            pred = scan.state == 1
            tp = np.sum(pred & truth)
            precision, recall = tp / max(pred.sum(), 1), tp / truth.sum()
            f1 = 2 * tp / (pred.sum() + truth.sum())
            rows.append((label, precision, recall, f1))
    print("| variant | precision | recall | F1 |")
    print("| --- | --- | --- | --- |")
    for label, p, r, f in rows:
        print(f"| {label} | {p:.4f} | {r:.4f} | {f:.4f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
