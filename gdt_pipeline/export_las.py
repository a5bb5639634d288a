"""LAS/LAZ 1.4 export of the twin's point sets for CloudCompare and GIS tools: one file per point set, its visible
points (the composite at the epoch), colours by change state, and the per-point values as named extra dimensions
(``change_state``, ``change_score``, ``p_value``, ``uncertainty``, ``source_epoch``, ``fusion_reason``,
``fusion_ratio``) that CloudCompare shows as scalar fields.

Coordinates are stored as integers of 0.1 mm (in the twin's units: 1e-4 for metres, 0.1 for millimetres) from an
offset at the set's lower corner, so georeferenced clouds keep their precision.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from twin_store import STATE_COLORS, ElementSet

from .errors import GdtError

RESOLUTION_M = 1e-4
# name, numpy type, description (LAS extra-bytes descriptions hold 32 characters)
EXTRA_DIMS = (
    ("change_state", np.uint8, "gdt:changeState code (0 same)"),
    ("change_score", np.float32, "dissimilarity score (NaN: none)"),
    ("p_value", np.float32, "p-value of the test (NaN: none)"),
    ("uncertainty", np.float32, "RMS sigma of the position"),
    ("source_epoch", np.int32, "index of the epoch it came from"),
    ("fusion_reason", np.uint8, "fusion reason code"),
    ("fusion_ratio", np.float32, "sqrt det cov ratio new/known"),
)


def _values(es: ElementSet, vis: np.ndarray) -> dict[str, np.ndarray]:
    n = int(vis.sum())
    nan = np.full(n, np.nan, dtype=np.float32)
    return {
        "change_state": np.asarray(es.state)[vis],
        "change_score": np.asarray(es.score, dtype=np.float32)[vis],
        "p_value": nan if es.p_value is None else np.asarray(es.p_value, dtype=np.float32)[vis],
        "uncertainty": np.asarray(es.uncertainty_summary, dtype=np.float32)[vis],
        "source_epoch": np.asarray(es.source_epoch)[vis],
        "fusion_reason": np.zeros(n, np.uint8) if es.reason is None else np.asarray(es.reason)[vis],
        "fusion_ratio": nan if es.reason_ratio is None else np.asarray(es.reason_ratio, dtype=np.float32)[vis],
    }


def write_las(es: ElementSet, path: Path, meters_per_unit: float) -> Path:
    """One point set's visible points as LAS 1.4 (LAZ when ``path`` ends in .laz), written beside and renamed."""
    import laspy

    vis = np.asarray(es.visible, dtype=bool)
    pts = np.asarray(es.points, dtype=np.float64)[vis]
    header = laspy.LasHeader(point_format=7, version="1.4")
    scale = RESOLUTION_M / meters_per_unit
    header.scales = np.full(3, scale)
    header.offsets = np.floor(pts.min(axis=0) / scale) * scale if len(pts) else np.zeros(3)
    header.add_extra_dims([laspy.ExtraBytesParams(name=name, type=dtype, description=doc)
                           for name, dtype, doc in EXTRA_DIMS])
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    rgb = np.round(STATE_COLORS[np.minimum(np.asarray(es.state)[vis], len(STATE_COLORS) - 1)] * 65535)
    las.red, las.green, las.blue = (rgb[:, k].astype(np.uint16) for k in range(3))
    for name, values in _values(es, vis).items():
        setattr(las, name, values)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        las.write(str(tmp))
    except Exception as exc:
        tmp.unlink(missing_ok=True)
        raise GdtError(f"could not write {path}: {type(exc).__name__}: {exc}") from exc
    os.replace(tmp, path)
    return path


def export_las(elements: list[ElementSet], out_dir: Path, meters_per_unit: float, compressed: bool = False
               ) -> list[Path]:
    """One LAS (or LAZ) per point set with visible points; meshes (CAD) are left to the PLY, OBJ and USD exports."""
    out_dir.mkdir(parents=True, exist_ok=True)
    suffix = ".laz" if compressed else ".las"
    return [write_las(es, out_dir / f"{es.key}{suffix}", meters_per_unit) for es in elements
            if es.kind == "points" and np.any(es.visible)]
