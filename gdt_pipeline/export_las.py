"""LAS/LAZ 1.4 export of the twin's point sets for CloudCompare and GIS tools: one file per point set, its visible
points (the composite at the epoch, or the part the epoch supplied: the scope of ``export_twin``), colours by change
state, the scan's own ASPRS classes where the twin kept them, and the per-point values as named extra dimensions
(``change_state``, ``change_score``, ``p_value``, ``uncertainty``, ``source_epoch``, ``fusion_reason``,
``fusion_ratio``; the table in ``export_values``, shared with the PLY export) that CloudCompare shows as scalar
fields.

Coordinates are stored as integers of 0.1 mm (in the twin's units: 1e-4 for metres, 0.1 for millimetres) from an
offset at the set's lower corner, so georeferenced clouds keep their precision.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twin_store import ElementSet, state_colours

from .export_values import VALUE_FIELDS, element_values, written_in_place

RESOLUTION_M = 1e-4


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
                           for name, dtype, doc in VALUE_FIELDS])
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    rgb = np.round(state_colours(np.asarray(es.state)[vis]) * 65535)
    las.red, las.green, las.blue = (rgb[:, k].astype(np.uint16) for k in range(3))
    for name, values in element_values(es, vis).items():
        setattr(las, name, values)
    if es.classification is not None:  # the scan file's own ASPRS classes go back where LAS tools look for them
        las.classification = np.asarray(es.classification, np.uint8)[vis]
    with written_in_place(path) as tmp:
        las.write(str(tmp))
    return path


def export_las(elements: list[ElementSet], out_dir: Path, meters_per_unit: float, compressed: bool = False
               ) -> list[Path]:
    """One LAS (or LAZ) per point set with visible points; meshes (CAD) are left to the PLY, OBJ and USD exports."""
    out_dir.mkdir(parents=True, exist_ok=True)
    suffix = ".laz" if compressed else ".las"
    return [write_las(es, out_dir / f"{es.key}{suffix}", meters_per_unit) for es in elements
            if es.kind == "points" and np.any(es.visible)]
