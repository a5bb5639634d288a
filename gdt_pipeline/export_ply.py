"""PLY export of the twin for CloudCompare, MeshLab and Open3D: one binary little-endian PLY per element set with its
visible elements (the composite at the epoch, or the part the epoch supplied: the scope of ``export_twin``).

A point set is a ``vertex`` element: double x, y, z (georeferenced clouds keep their precision), uchar red, green,
blue by change state (or the set's display colour), and the values of the LAS export as scalar properties (the
table in ``export_values``: ``change_state``, ``change_score``, ``p_value``, ``uncertainty``, ``source_epoch``,
``fusion_reason``, ``fusion_ratio``). A mesh is a ``vertex`` element (double x, y, z: every vertex of the set, so
the indices stay the twin's) and a ``face`` element with ``vertex_indices``, the colour and the same scalar
properties per facet. The header's comments describe each property and name the twin's units.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twin_store import ElementSet, display_colours

from .export_values import CODE_NAMES, VALUE_FIELDS, element_values, written_in_place
from .names import unit_name


def ply_comments(kind: str, meters_per_unit: float) -> list[str]:
    """The header comments of a set's PLY: its units, where the values sit, then what each property holds."""
    unit = unit_name(meters_per_unit)
    where = "per facet (face element)" if kind == "mesh" else "per point (vertex element)"
    lines = [f"units: {unit} (1 unit = {meters_per_unit:g} m)",
             f"{where}: red green blue by change state (or the set's display colour) and the scalar properties below"]
    for name, _, doc in VALUE_FIELDS:
        codes = ", ".join(f"{i}={n}" for i, n in enumerate(CODE_NAMES.get(name, ())))
        lines.append(f"{name}: {doc}" + (f"; codes {codes}" if codes else ""))
    return lines


def _colours(es: ElementSet, selected: np.ndarray) -> np.ndarray:
    rgb = display_colours(es)
    return np.round(np.clip(rgb[selected], 0.0, 1.0) * 255).astype(np.uint8)


def _table(columns: dict[str, np.ndarray]) -> np.ndarray:
    """One little-endian record per row of the columns (a column of shape (n, k) becomes a field of k values)."""
    first = next(iter(columns.values()))
    out = np.empty(len(first), [(name, col.dtype.newbyteorder("<"), col.shape[1:]) for name, col in columns.items()])
    for name, col in columns.items():
        out[name] = col
    return out


def _with_values(head: dict[str, np.ndarray], es: ElementSet, selected: np.ndarray) -> np.ndarray:
    """A record per selected element: the ``head`` columns, red, green, blue, then the value fields."""
    rgb = dict(zip(("red", "green", "blue"), _colours(es, selected).T, strict=True))
    return _table({**head, **rgb, **element_values(es, selected)})


def _body(records: np.ndarray) -> bytes:
    """An element's binary body: a fixed-length list field as PLY stores it, a uchar count before its values."""
    fields, counts = [], {}
    for name in records.dtype.names:
        sub = records.dtype[name]
        if sub.shape:
            counts[f"{name}__count"] = sub.shape[0]
            fields.append((f"{name}__count", np.uint8))
        fields.append((name, sub))
    packed = np.empty(len(records), fields)
    for name, n in counts.items():
        packed[name] = n
    for name in records.dtype.names:
        packed[name] = records[name]
    return packed.tobytes()


def write_ply(path: Path, elements: dict[str, np.ndarray], comments: list[str]) -> Path:
    """Binary little-endian PLY of named record arrays (fixed-length array fields become PLY lists), renamed in."""
    from plyfile import PlyData, PlyElement

    header = PlyData([PlyElement.describe(rec, name) for name, rec in elements.items()], byte_order="<",
                     comments=comments).header
    with written_in_place(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header.encode("ascii") + b"\n")
        # plyfile writes an element with a list property record by record (about 14 s per million facets);
        # the lists here all have three entries, so numpy writes the same bytes at once
        for rec in elements.values():
            fh.write(_body(rec))
    return path


def export_ply(elements: list[ElementSet], out_dir: Path, meters_per_unit: float = 1.0) -> list[Path]:
    """One PLY per element set with visible elements: points with their values, or meshes with them per facet."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for es in elements:
        vis = np.asarray(es.visible, dtype=bool)
        if not vis.any():
            continue
        pts = np.asarray(es.points, dtype=np.float64)
        if es.kind == "mesh":
            face = _with_values({"vertex_indices": np.asarray(es.faces, dtype=np.int32)[vis]}, es, vis)
            records = {"vertex": _table({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}), "face": face}
        else:
            records = {"vertex": _with_values({"x": pts[vis, 0], "y": pts[vis, 1], "z": pts[vis, 2]}, es, vis)}
        written.append(write_ply(out_dir / f"{es.key}.ply", records, ply_comments(es.kind, meters_per_unit)))
    return written
