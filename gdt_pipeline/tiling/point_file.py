"""A tiled run's scans kept in a scratch file instead of in memory (``docs/scale.md``).

Once the tiles are cut, the epoch's scans are read row by row: a tile takes its members' points (a gather of
rows), the fusion the changed ones, the writer a run of rows per part. Held in memory they are 24 B a point for the
whole run, 1.2 GB at 50 M points; in an unnamed scratch file, mapped read-only as a ``MappedRows``, they are on disk
and in the page cache, and the process holds the rows a reader takes, a piece at a time.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..scratch import scratch_file, write_at
from ..types import Dataset, MappedRows

# Rows written to the scratch file at a time: 6 MB of points, so that writing holds no copy of the scan.
WRITE_PIECE = 1 << 18
POINT_BYTES = 24


def spilled_points(ds: Dataset, folder: Path) -> Dataset:
    """``ds`` with its points in a scratch file in ``folder``, read-only and mapped; a mesh (whose vertices every
    facet needs), an empty set and points already in a scratch file come back as they are."""
    if ds.faces is not None or len(ds.points) == 0 or isinstance(ds.points, MappedRows):
        return ds
    n = len(ds.points)
    room = f"{n * POINT_BYTES / 1e9:.3g} GB of points"
    file = scratch_file(folder, "gdt-points-")
    try:
        for start in range(0, n, WRITE_PIECE):
            write_at(file, ds.points[start:start + WRITE_PIECE], start * POINT_BYTES, folder,
                     f"dataset {ds.name!r} points", room)
        # the map keeps the file open; the descriptor goes when this block ends
        rows = MappedRows(file, dtype=np.float64, mode="r", shape=(n, 3))
    finally:
        file.close()
    return dataclasses.replace(ds, points=rows)
