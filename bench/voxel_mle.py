"""Voxel MLE throughput and peak memory on 5 M points (a dense, noisy ToF-like cloud of a room-sized scene).

Prints points/s and peak resident memory, for the default overlap (0.5: 8 voxels per point) and for none.
Run: make bench
"""

from __future__ import annotations

import resource
import sys
import time

import numpy as np

from stages.uncertainty.estimators import voxel_mle


def main() -> int:
    """Run the benchmark and print its figures."""
    n = 5_000_000
    rng = np.random.default_rng(0)
    # points on the six faces of a 4 x 3 x 2.5 m room, 1 cm noise
    face = rng.integers(0, 6, n)
    u, v = rng.random(n), rng.random(n)
    size = np.array([4.0, 3.0, 2.5])
    pts = np.column_stack([u, v, np.zeros(n)])
    axes = [(0, 1, 2), (0, 1, 2), (0, 2, 1), (0, 2, 1), (2, 1, 0), (2, 1, 0)]
    out = np.empty_like(pts)
    for f, (a, b, c) in enumerate(axes):
        sel = face == f
        out[sel, a], out[sel, b] = pts[sel, 0] * size[a], pts[sel, 1] * size[b]
        out[sel, c] = size[c] * (f % 2)
    out += rng.normal(0, 0.01, out.shape)
    base_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"voxel MLE on {n:,} points (input {out.nbytes / 1e6:.0f} MB, process peak before: {base_mb:,.0f} MB)")
    for steps, label in ((2, "overlap 0.5 (8 voxels/point)"), (1, "no overlap")):
        t0 = time.perf_counter()
        mean, _cov, _counts = voxel_mle(out, voxel=0.1, overlap_steps=steps, min_points=10, min_sigma=0.001)
        dt = time.perf_counter() - t0
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(f"  {label:<30} {dt:6.2f} s  {n / dt:12,.0f} points/s  {len(mean):9,} Gaussians  "
              f"peak RSS {peak:,.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
