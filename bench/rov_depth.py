"""Region-of-view cost per million recent points: the depth-image stage (``sight: depth``, the default) against the
Plane-of-Sight one (``sight: plane``, ball pivoting of the whole cloud), on the same simulated scans.

A 3 × 2 m floor with 40 boxes (the CAD, 12 facets each plus the floor's two), one removed; two to eight pinhole
stations 2.5 m away scan it with the structured-light profile at a density that gives the point count asked for.
Prints per size the median of three runs: seconds, seconds per million points and peak RSS growth.

    .venv/bin/python bench/rov_depth.py [--sizes 250000,1000000,2000000] [--plane-up-to 250000]
"""

from __future__ import annotations

import argparse
import logging
import resource
import time
from pathlib import Path

import numpy as np
import trimesh

from gdt_pipeline import Composite, CompositeItem, Dataset, EpochInfo, GaussianUncertainty
from gdt_pipeline.plugins import StageContext, load_registry
from gdt_pipeline.sensors import PRESETS
from gdt_pipeline.simulation.scanner import ScannerSpec, simulate_scan


def scene(rng: np.random.Generator) -> tuple[list, list]:
    """The CAD (floor and 40 boxes) and the as-is meshes (one box removed)."""
    floor = trimesh.creation.box(extents=(3.0, 2.0, 0.02))
    floor.apply_translation((0, 0, -0.01))
    boxes = []
    for x in np.linspace(-1.3, 1.3, 8):
        for y in np.linspace(-0.8, 0.8, 5):
            b = trimesh.creation.box(extents=tuple(rng.uniform(0.08, 0.2, 3)))
            b.apply_translation((x, y, b.extents[2] / 2))
            boxes.append(b)
    return [floor, *boxes], [floor, *boxes[1:]]


def scans(asis: list, n_points: int, rng: np.random.Generator) -> list[Dataset]:
    """Stations around the scene, dense enough for about ``n_points`` in all, with the profile's covariance."""
    n_st = int(np.clip(n_points // 250_000, 2, 8))
    az = np.linspace(0, 2 * np.pi, n_st, endpoint=False)
    out = []
    for k, a in enumerate(az):
        eye = np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 1.5])
        spec = ScannerSpec(fov_deg=70.0, points_per_m2=1.0, max_range=10.0, profile="structured_light")
        probe = simulate_scan(asis, eye, np.zeros(3), spec, rng)
        density = max(1.0, (n_points / n_st) / max(len(probe.points), 1))
        spec = spec.model_copy(update={"points_per_m2": density})
        s = simulate_scan(asis, eye, np.zeros(3), spec, rng)
        d = s.clean - eye
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        dd = d[:, :, None] * d[:, None, :]
        cov = s.sigma_range[:, None, None] ** 2 * dd + s.sigma_lateral[:, None, None] ** 2 * (np.eye(3) - dd)
        out.append(Dataset(f"scan{k}", "as-is", s.points, viewpoints=eye[None]).with_uncertainty(
            GaussianUncertainty(cov)))
    return out


def run(registry, sight: str, recent: list[Dataset], reference: Composite) -> tuple[float, float]:
    """Seconds and peak RSS growth (MB) of one region-of-view run."""
    spec = registry.get("manual_box")
    info = EpochInfo(id="E1", index=1, role="as-is", seed=0, workflow_dir=Path("."), units="m")
    ctx = StageContext(stage=spec, params=spec.params(lower=[-2, -2, -0.5], upper=[2, 2, 1], sight=sight),
                       slots={"recent": recent, "reference": reference, "epoch": info}, epoch=info,
                       rng=np.random.default_rng(0), seed=0, log=logging.getLogger("bench"))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    spec.run(ctx)
    return time.perf_counter() - t0, (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024


def main() -> None:
    """Time both modes at each size and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="250000,1000000,2000000")
    ap.add_argument("--plane-up-to", type=int, default=250_000, help="Largest size the ball-pivoting mode runs at.")
    args = ap.parse_args()
    rng = np.random.default_rng(7)
    cad, asis = scene(rng)
    reference = Composite(tuple(CompositeItem(f"E0_part{i}", Dataset(f"part{i}", "as-designed", m.vertices,
                                                                       faces=m.faces),
                                              "E0", np.zeros(len(m.faces), np.uint8), np.full(len(m.faces), np.nan),
                                              np.zeros(len(m.faces), np.int32), np.ones(len(m.faces), bool))
                                for i, m in enumerate(cad)))
    registry = load_registry()
    assert PRESETS["structured_light"]
    print(f"{'points':>10} {'mode':>6} {'s (median of 3)':>16} {'s per M points':>15} {'peak RSS +MB':>13}")
    for size in (int(s) for s in args.sizes.split(",")):
        recent = scans(asis, size, rng)
        n = sum(ds.n_elements for ds in recent)
        for sight in ("depth", "plane"):
            if sight == "plane" and size > args.plane_up_to:
                continue
            runs = [run(registry, sight, recent, reference) for _ in range(3)]
            sec = float(np.median([r[0] for r in runs]))
            print(f"{n:>10,} {sight:>6} {sec:>16.2f} {sec / n * 1e6:>15.2f} {max(r[1] for r in runs):>13.0f}",
                  flush=True)


if __name__ == "__main__":
    main()
