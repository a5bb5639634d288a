"""Throughput of the built-in chain on real data: glassfire TLS 2021 (0.4 M points) against 2020 (0.6 M points).

Prints points/s per stage and the peak resident memory. Skips (exit 0, with a reason) when ../shared/data is absent.
Run: make bench
"""

from __future__ import annotations

import resource
import sys
import time
from pathlib import Path

import numpy as np

from gdt_pipeline import ChangeState, Composite, CompositeItem, Dataset, GaussianUncertainty
from gdt_pipeline.geometry import ReferenceIndex
from stages.distance import bhattacharyya_gaussian

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "glassfire_tls"


def _read(path: Path) -> np.ndarray:
    import laspy

    las = laspy.read(str(path))
    return np.column_stack([las.x, las.y, las.z]).astype(np.float64)


def main() -> int:
    """Run the benchmark and print its figures."""
    if not (DATA / "glassfire_2020.laz").is_file():
        print(f"skipped: {DATA} not found (the shared real data is not on this machine)")
        return 0
    ref_pts, new_pts = _read(DATA / "glassfire_2020.laz"), _read(DATA / "glassfire_2021.laz")
    sigma = 0.125 / np.sqrt(12)  # voxel-centre quantisation of the 0.125 m grid, as an isotropic sigma
    unc = GaussianUncertainty.isotropic(sigma)
    ref = Dataset("tls2020", "as-is", ref_pts, uncertainty=unc)
    new = Dataset("tls2021", "as-is", new_pts, uncertainty=unc)
    n = ref.n_elements
    comp = Composite((CompositeItem("E0_tls2020", ref, "E0", np.zeros(n), np.full(n, np.nan), np.zeros(n),
                                    np.ones(n, bool)),))
    t0 = time.perf_counter()
    index = ReferenceIndex(comp)
    t1 = time.perf_counter()
    res = index.nearest(new.element_positions(), max_distance=1.0)
    t2 = time.perf_counter()
    found = res.item >= 0
    cov = unc.covariance(new.n_elements)
    bd = bhattacharyya_gaussian(new.points[found], cov[found], res.position[found], cov[found])
    t3 = time.perf_counter()
    changed = int(np.sum(bd > 4.0)) + int(np.sum(~found))
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    m = new.n_elements
    print(f"glassfire TLS: {m:,} query points against {n:,} reference points")
    print(f"  index build        {t1 - t0:7.3f} s")
    print(f"  nearest (cKDTree)  {t2 - t1:7.3f} s   {m / (t2 - t1):12,.0f} points/s")
    print(f"  bhattacharyya      {t3 - t2:7.3f} s   {found.sum() / (t3 - t2):12,.0f} pairs/s")
    print(f"  chain total        {t3 - t0:7.3f} s   {m / (t3 - t0):12,.0f} points/s")
    print(f"  changed (BD > 4 or no partner within 1 m): {changed:,} ({changed / m:.1%}); "
          f"state codes {int(ChangeState.NEW)}=new")
    print(f"  peak RSS {peak_mb:,.0f} MB")
    print("  peer (shared/data/README.md): py4dgeo M3C2 on 600,000 core points, 12.3 s (~49 k/s), 360 MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
