"""An upper bound for change detection on suite scenes: an oracle that knows the true segmentation. Every scan
point's noise-free offset from the CAD along its beam is pooled over the points its ray hit on the same true part
face (object and facet). A face is called changed when its mean offset exceeds 3 standard errors of that pooled
mean (its points' range σ over √n). The changed points of such faces are found, the rest missed; nothing unchanged
is flagged. No method that pools whole faces can do better, so a scene's oracle F1 bounds what one epoch of its
scans can show.

    .venv/bin/python bench/oracle.py out/bench/expectation    # the scenes bench/expectation.py wrote (--out)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import trimesh

from gdt_pipeline.geometry import raycasting_scene

SIGMAS = 3.0


def face_offsets(cad_scene: object, eye: np.ndarray, truth: dict) -> np.ndarray:
    """Per point: the noise-free point's range beyond the CAD along its beam (10 m where the beam misses it)."""
    import open3d as o3d

    beam = truth["clean"] - eye
    rng = np.linalg.norm(beam, axis=1)
    rays = np.hstack([np.broadcast_to(eye, beam.shape), beam / rng[:, None]]).astype(np.float32)
    hit = cad_scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    return np.where(np.isfinite(hit), rng - hit, 10.0)


def oracle_found(offset: np.ndarray, truth: dict) -> np.ndarray:
    """Per point: whether the oracle calls its true face changed."""
    key = truth["object_id"].astype(np.int64) * 1_000_000 + truth["facet_id"]
    _, face = np.unique(key, return_inverse=True)
    count = np.bincount(face)
    mean = np.bincount(face, offset) / count
    variance = np.bincount(face, truth["sigma_range"] ** 2) / count
    return (np.abs(mean) > SIGMAS * np.sqrt(variance / count))[face]


def scene_f1(root: Path) -> float:
    """The oracle's change F1 over all E1 scans of one suite scene."""
    meta = json.loads((root / "scene.json").read_text(encoding="utf-8"))
    cad_scene = raycasting_scene([trimesh.load(p, force="mesh") for p in sorted(root.glob("cad_*.obj"))])
    tp = flagged = changed = 0
    for k, station in enumerate(meta["stations"]):
        truth = dict(np.load(root / f"scan_E1_s{k}_truth.npz"))
        is_changed = truth["changed"].astype(bool)
        found = oracle_found(face_offsets(cad_scene, np.asarray(station["eye"], dtype=np.float64), truth), truth)
        found &= is_changed  # the oracle flags nothing unchanged
        tp, flagged, changed = tp + int(found.sum()), flagged + int(found.sum()), changed + int(is_changed.sum())
    return 2 * tp / (flagged + changed) if flagged + changed else 1.0


def main(argv: list[str]) -> int:
    if len(argv) != 1 or not Path(argv[0]).is_dir():
        print(__doc__)
        return 2
    scenes = sorted(p for p in Path(argv[0]).glob("scene_*") if (p / "scene.json").is_file())
    if not scenes:
        print(f"no suite scenes (scene_*/scene.json) under {argv[0]}")
        return 2
    scores = []
    for root in scenes:
        scores.append(scene_f1(root))
        print(f"{root.name}: oracle F1 {scores[-1]:.3f}", flush=True)
    print(f"oracle: mean F1 {np.mean(scores):.4f}  worst {min(scores):.3f}  (n={len(scores)})")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
