"""Pairs/s of the Bhattacharyya distance at 1 M pairs: Gaussian–Gaussian (closed form), Gaussian–box aligned
(closed form) and turned (Genz quadrature, ε = 1e-6), against a plain numpy Euclidean distance on the same arrays.

Run: make bench
"""

from __future__ import annotations

import resource
import sys
import time

import numpy as np
from scipy.spatial.transform import Rotation

from gdt_pipeline import BoxUncertainty
from stages.distance.bhattacharyya_maths import bc_gauss_box, bd_gauss_gauss


def _timed(fn, *args, **kw) -> float:
    t0 = time.perf_counter()
    fn(*args, **kw)
    return time.perf_counter() - t0


def main() -> int:
    """Run the benchmark and print its figures."""
    n = 1_000_000
    rng = np.random.default_rng(0)
    rots = Rotation.random(n, random_state=1).as_matrix()
    c1 = rots @ np.diag([4e-6, 1e-6, 2.5e-7]) @ np.swapaxes(rots, 1, 2)
    c2 = np.broadcast_to(np.eye(3) * 1e-6, (n, 3, 3)).copy()
    m1, m2 = rng.normal(0, 0.001, (n, 3)), rng.normal(0, 0.001, (n, 3))
    t_euc = _timed(lambda: np.linalg.norm(m1 - m2, axis=1))
    t_gg = _timed(bd_gauss_gauss, m1, c1, m2, c2)
    box = BoxUncertainty(np.array([[0.002, 0.0015, 0.001]]))
    t_gb_aligned = _timed(bc_gauss_box, m1, c2, m2, box)
    k = 100_000  # the turned case is slower: time a tenth and scale
    t_gb_turned = _timed(bc_gauss_box, m1[:k], c1[:k], m2[:k], box, eps=1e-6) * (n / k)
    print(f"Bhattacharyya distance, {n:,} pairs (peak RSS "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:,.0f} MB at the end)")
    print(f"  numpy Euclidean distance (peer)      {n / t_euc:14,.0f} pairs/s")
    for label, t in (("Gaussian–Gaussian, closed form", t_gg), ("Gaussian–box, axes aligned", t_gb_aligned),
                     ("Gaussian–box, turned (eps 1e-6)", t_gb_turned)):
        print(f"  {label:<36} {n / t:14,.0f} pairs/s   {t / t_euc:7.1f}x the Euclidean time")
    return 0


if __name__ == "__main__":
    sys.exit(main())
