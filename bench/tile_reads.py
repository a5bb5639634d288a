"""Reading one tile of a large LAS, LAZ and COPC file (issue 36): the whole read against box reads, side by side.

A plant room (floor, walls, pipes, cabinets) scanned from four stations, each station's points in its scanner's
order (by azimuth, then elevation), written as one file of ``--points`` points: LAS and LAZ with laspy, COPC with
copc-lib. For each file, in a fresh process each:

- ``whole``: ``read_las`` of the whole file (what a run does today);
- ``tiles``: the file opened for box reads (LAS/LAZ: the first-pass index; COPC: its octree) and every tile of a
  grid of about ``--tile-points`` points read in turn, each let go before the next;
- ``sorted`` (LAS/LAZ): the same, with the points first sorted by cell into a scratch file (a second pass).

Printed: seconds, points/s, peak RSS of the process (VmHWM) and above what importing the readers took (the
engine's libraries), bytes per point of the file, how many rows a tile decodes for each point it returns, and a
check that the tiles' elements cover every element of the file (the shared faces of closed boxes counted once) with
the whole read's coordinates.

    .venv/bin/python bench/tile_reads.py --points 20000000 --tile-points 1000000
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

STATIONS = ((2.0, 2.0, 1.5), (8.0, 2.5, 1.4), (3.0, 6.0, 1.6), (9.0, 6.5, 1.5))
ROOM = np.array([12.0, 8.0, 3.5])


def _surfaces(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points on a plant room's floor, walls, ceiling, three pipes and two cabinets, 1 mm noise."""
    shares = np.array([0.22, 0.28, 0.12, 0.22, 0.16])
    counts = rng.multinomial(n, shares / shares.sum())
    floor_ceiling = rng.uniform(0, 1, (counts[0], 3)) * ROOM
    floor_ceiling[:, 2] = np.where(rng.random(counts[0]) < 0.7, 0.0, ROOM[2])
    walls = rng.uniform(0, 1, (counts[1], 3)) * ROOM
    side = rng.integers(0, 4, counts[1])
    walls[side == 0, 0], walls[side == 1, 0] = 0.0, ROOM[0]
    walls[side == 2, 1], walls[side == 3, 1] = 0.0, ROOM[1]
    shelf = rng.uniform(0, 1, (counts[2], 3)) * [ROOM[0], 0.6, 2.0] + [0, 7.2, 0]
    t, h = rng.uniform(0, 2 * np.pi, counts[3]), rng.uniform(0, ROOM[0], counts[3])
    which = rng.integers(0, 3, counts[3])
    centre_y, centre_z, radius = np.array([2.0, 4.0, 5.5])[which], np.array([2.8, 3.0, 2.6])[which], 0.15 + 0.1 * which
    pipes = np.column_stack([h, centre_y + radius * np.cos(t), centre_z + radius * np.sin(t)])
    box = rng.uniform(0, 1, (counts[4], 3)) * [1.2, 0.8, 1.8] + [5.0, 3.2, 0.0]
    face = rng.integers(0, 3, counts[4])
    box[face == 0, 0] = 5.0 + 1.2 * rng.integers(0, 2, int((face == 0).sum()))
    box[face == 1, 1] = 3.2 + 0.8 * rng.integers(0, 2, int((face == 1).sum()))
    box[face == 2, 2] = 1.8
    pts = np.concatenate([floor_ceiling, walls, shelf, pipes, box])
    return pts + rng.normal(0, 0.001, pts.shape)


def survey(n: int, seed: int = 0) -> np.ndarray:
    """The four stations' points, each station's in scan order (azimuth, then elevation), stations one after another."""
    rng = np.random.default_rng(seed)
    parts = []
    for k, station in enumerate(STATIONS):
        m = n // len(STATIONS) + (n % len(STATIONS) if k == 0 else 0)
        pts = _surfaces(m, rng)
        d = pts - station
        azimuth = np.round(np.arctan2(d[:, 1], d[:, 0]) * 2000)  # 2000 columns a radian, rows within a column
        elevation = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
        parts.append(pts[np.lexsort((elevation, azimuth))])
    return np.round(np.concatenate(parts) / 1e-4) * 1e-4


def write_inputs(folder: Path, n: int) -> dict[str, Path]:
    """The survey as LAS, LAZ (laspy) and COPC (copc-lib), written once per size."""
    import laspy

    from gdt_pipeline.simulation.copc_file import write_copc

    folder.mkdir(parents=True, exist_ok=True)
    paths = {fmt: folder / f"survey_{n}.{ext}" for fmt, ext in (("las", "las"), ("laz", "laz"),
                                                               ("copc", "copc.laz"))}
    if all(p.exists() for p in paths.values()):
        return paths
    pts = survey(n)
    intensity = (np.linalg.norm(pts - ROOM / 2, axis=1) * 4000).astype(np.uint16)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = [1e-4] * 3, [0.0, 0.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts.T
    las.intensity = intensity
    las.write(str(paths["las"]))
    las.write(str(paths["laz"]))
    del las
    write_copc(paths["copc"], pts, scale=1e-4, intensity=intensity)
    return paths


def _tiles(lower: np.ndarray, upper: np.ndarray, count: int, tile_points: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """A grid of cubes over the extent with about ``tile_points`` points each on average (the tiles' boxes)."""
    n_tiles = max(1, round(count / tile_points))
    span = np.maximum(upper - lower, 1e-9)
    size = float(np.prod(span) / n_tiles) ** (1 / 3)
    shape = np.maximum(1, np.ceil(span / size).astype(int))
    edges = [np.linspace(lo, hi, k + 1) for lo, hi, k in zip(lower, upper, shape, strict=True)]
    return [(np.array([edges[0][i], edges[1][j], edges[2][k]]), np.array([edges[0][i + 1], edges[1][j + 1],
                                                                           edges[2][k + 1]]))
            for i in range(shape[0]) for j in range(shape[1]) for k in range(shape[2])]


def _rows_read(source: Any, lower: np.ndarray, upper: np.ndarray) -> int:
    """Rows a box read decodes: the runs or nodes it reads, or with a cell-sorted scratch file its cells' rows."""
    if source.cache is not None:
        cells = source.cache.grid.cells_in(lower, upper)
        return int(np.sum(source.cache.starts[cells + 1] - source.cache.starts[cells]))
    rows = np.diff(source.index.rows)
    return int(rows[source.index.chunks(lower, upper)].sum())


def measure(path: Path, way: str, tile_points: int) -> dict[str, object]:
    """One way of reading ``path``, in this process (run as a child, so that its peak RSS is its own)."""
    from gdt_pipeline.memory import peak_rss_mb
    from stages.io.las import read_las
    from stages.io.las_boxes import open_las_boxes

    base = peak_rss_mb()
    start = time.perf_counter()
    out: dict[str, object] = {}
    if way == "whole":
        pts, _ = read_las(path, None, ("intensity",))
        out.update(points=len(pts), checksum=float(pts.sum()))
    else:
        source = open_las_boxes(path, None, ("intensity",), sort_cells=way == "sorted")
        out["index_s"] = time.perf_counter() - start
        seen = np.zeros(source.count, bool)
        total, largest, read, checksum, times = 0, 0, 0, 0.0, []
        for lo, hi in _tiles(source.lower, source.upper, source.count, tile_points):
            t0 = time.perf_counter()
            box = source.read_box(lo, hi)
            times.append(time.perf_counter() - t0)
            fresh = ~seen[box.elements]
            checksum += float(box.points[fresh].sum())
            seen[box.elements] = True
            total += len(box.elements)
            largest = max(largest, len(box.elements))
            read += _rows_read(source, lo, hi)
            del box
        source.close()
        out.update(points=int(seen.sum()), every_element=bool(seen.all()), checksum=checksum, tiles=len(times),
                   tile_points_read=total, largest_tile=largest, tile_median_s=float(np.median(times)),
                   read_per_returned=read / max(total, 1))
    out["seconds"] = time.perf_counter() - start
    out["peak_rss_mb"] = peak_rss_mb()
    out["start_rss_mb"] = base
    return out


def main() -> None:
    """Write the inputs, then read each way in a child process and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=20_000_000)
    ap.add_argument("--tile-points", type=int, default=1_000_000)
    ap.add_argument("--formats", default="las,laz,copc")
    ap.add_argument("--data", type=Path, default=ROOT / "out" / "bench" / "tile_reads")
    ap.add_argument("--child", nargs=2, metavar=("PATH", "WAY"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure(Path(args.child[0]), args.child[1], args.tile_points)))
        return
    t0 = time.perf_counter()
    paths = write_inputs(args.data, args.points)
    print(f"inputs ready in {time.perf_counter() - t0:.1f} s", flush=True)
    print("| format | file | way | seconds | points/s | peak RSS (above imports) | B/point above imports | tiles |"
          " largest tile | rows decoded a point returned | index (and sort) | every element, same coordinates |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for fmt in args.formats.split(","):
        path = paths[fmt]
        size_mb = path.stat().st_size / 2**20
        results = {}
        for way in ("whole", "tiles", "sorted") if fmt != "copc" else ("whole", "tiles"):
            child = subprocess.run([sys.executable, __file__, "--child", str(path), way, "--tile-points",
                                    str(args.tile_points)], capture_output=True, text=True, check=True)
            results[way] = r = json.loads(child.stdout.strip().splitlines()[-1])
            n = int(r["points"])
            above = r["peak_rss_mb"] - r["start_rss_mb"]
            same = "–" if way == "whole" else (
                f"{r['every_element']}, {abs(r['checksum'] - results['whole']['checksum']) < 1e-6 * n}")
            tiles = (f"{r['tiles']} | {r['largest_tile']:,} | {r['read_per_returned']:.2f} | {r['index_s']:.1f} s"
                     if way != "whole" else "– | – | – | –")
            print(f"| {fmt} | {size_mb:,.0f} MB | {way} | {r['seconds']:.1f} | {n / r['seconds'] / 1e6:.2f} M | "
                  f"{r['peak_rss_mb']:,.0f} MB ({above:,.0f} MB) | {above * 2**20 / n:.1f} | {tiles} | {same} |",
                  flush=True)


if __name__ == "__main__":
    main()
