"""Point clouds: PLY and the text formats (XYZ, XYZN, XYZRGB, PTS) read and checked here; PCD checked here, then
read by Open3D. Open3D skips text lines it cannot parse, fills zeros for tokens it cannot read and returns a filled
array after printing "Read ... failed", so nothing it returns is trusted without the file's own counts.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from gdt_pipeline import Dataset, InputError, ReaderSpec, ReadRequest

from .ply import read_ply
from .ply_header import face_count, read_header
from .text import Rows, check_finite, check_integral, table
from .version import VERSION

# Columns of the XYZ family (Open3D reads the first three as the coordinates).
TEXT_COLUMNS = {".xyz": 3, ".xyzn": 6, ".xyzrgb": 6}
_PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_NORMALS = {"normal_x", "normal_y", "normal_z"}
_PCD_TYPES = {("F", 4), ("F", 8), ("I", 1), ("I", 2), ("I", 4), ("I", 8), ("U", 1), ("U", 2), ("U", 4), ("U", 8)}


def read_xyz(path: Path) -> np.ndarray:
    """An XYZ/XYZN/XYZRGB file: every non-blank line the same count of numbers, finite coordinates."""
    with open(path, "rb") as fh:
        rows = Rows.of(fh.read())
    if not rows.lines:
        raise InputError(f"{path}: no points (only blank lines)")
    what = f"{path.suffix.lower().lstrip('.').upper()} row"
    mat = table(rows, path, what, min_columns=TEXT_COLUMNS.get(path.suffix.lower(), 3))
    check_finite(mat[:, :3], rows, path, what)
    return np.ascontiguousarray(mat[:, :3])


def read_pts(path: Path) -> np.ndarray:
    """A PTS file: a count line, then exactly that many rows of x y z [intensity] [r g b]."""
    with open(path, "rb") as fh:
        rows = Rows.of(fh.read())
    first = rows.lines[0].split() if rows.lines else []
    if len(first) != 1:
        where = f"line {rows.numbers[0]}" if rows.lines else "line 1"
        raise InputError(f"{path}: {where}: a PTS file starts with the point count alone on its line")
    count = int(check_integral(table(rows.take(0, 1), path, "PTS point count"), rows, path, "PTS point count")[0, 0])
    body = rows.take(1, len(rows.lines))
    if count != len(body.lines):
        raise InputError(f"{path}: line {rows.numbers[0]} declares {count} points, the file holds "
                         f"{len(body.lines)} rows")
    if count == 0:
        raise InputError(f"{path}: line {rows.numbers[0]} declares 0 points")
    mat = table(body, path, "PTS row", min_columns=3)
    check_finite(mat[:, :3], body, path, "PTS row")
    return np.ascontiguousarray(mat[:, :3])


def _pcd_header(path: Path) -> tuple[dict[str, list[str]], int, int]:
    """The PCD header's fields by keyword, the byte offset where the data starts and the line after DATA."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    fields: dict[str, list[str]] = {}
    offset = 0
    for number, raw in enumerate(head.split(b"\n")[:-1], start=1):
        offset += len(raw) + 1
        line = raw.decode("latin-1").split("#", 1)[0].split()
        if not line:
            continue
        if line[0].upper() not in _PCD_KEYS or line[0].upper() in fields:
            raise InputError(f"{path}: PCD header line {number}: unexpected {raw[:40].decode('latin-1')!r} (the "
                             f"header holds each of {' '.join(_PCD_KEYS)} once)")
        fields[line[0].upper()] = line[1:]
        if line[0].upper() == "DATA":
            return fields, offset, number + 1
    raise InputError(f"{path}: no DATA line in the PCD header (not a PCD file or a truncated header)")


def _pcd_ints(fields: dict[str, list[str]], key: str, path: Path, default: list[str] | None = None) -> list[int]:
    values = fields.get(key, default)
    if values is None or not values or not all(v.isdigit() for v in values):
        raise InputError(f"{path}: PCD header field {key} is {values!r}, expected non-negative integers")
    return [int(v) for v in values]


def _pcd_layout(fields: dict[str, list[str]], path: Path) -> tuple[int, int, int]:
    """(points, values per row, bytes per row) as the header declares them, checked against each other."""
    names = fields.get("FIELDS", [])
    if not {"x", "y", "z"} <= set(names):
        raise InputError(f"{path}: PCD header field FIELDS is {names}, it needs x y z")
    # Open3D reads past its buffers (a segfault) when only some of the normal fields are there.
    if len(set(names)) != len(names) or 0 < len(_NORMALS & set(names)) < 3:
        raise InputError(f"{path}: PCD header field FIELDS is {names}: names must be unique and normal_x normal_y "
                         f"normal_z come together")
    size = _pcd_ints(fields, "SIZE", path)
    count = _pcd_ints(fields, "COUNT", path, ["1"] * len(names))
    types = fields.get("TYPE", [])
    if not len(names) == len(size) == len(types) == len(count):
        raise InputError(f"{path}: PCD header fields FIELDS ({len(names)}), SIZE ({len(size)}), TYPE ({len(types)}) "
                         f"and COUNT ({len(count)}) must list one entry per field")
    bad = [f"{t}{s}" for t, s in zip(types, size, strict=True) if (t.upper(), s) not in _PCD_TYPES]
    if bad:
        raise InputError(f"{path}: PCD header field TYPE/SIZE has unknown types {bad}")
    width, height = _pcd_ints(fields, "WIDTH", path)[0], _pcd_ints(fields, "HEIGHT", path, ["1"])[0]
    points = _pcd_ints(fields, "POINTS", path, [str(width * height)])[0]
    if width * height != points:
        raise InputError(f"{path}: PCD header WIDTH × HEIGHT = {width} × {height} = {width * height}, but "
                         f"POINTS = {points}")
    return points, sum(count), sum(s * c for s, c in zip(size, count, strict=True))


def check_pcd(path: Path) -> int:
    """The point count a PCD declares, with its data section checked against it (rows/tokens or bytes)."""
    fields, offset, line = _pcd_header(path)
    points, values, row_bytes = _pcd_layout(fields, path)
    data = (fields.get("DATA") or ["?"])[0].lower()
    file_size = path.stat().st_size
    if data == "ascii":
        with open(path, "rb") as fh:
            fh.seek(offset)
            rows = Rows.of(fh.read(), first_line=line)
        if len(rows.lines) != points:
            raise InputError(f"{path}: PCD header declares POINTS {points}, the data holds {len(rows.lines)} rows")
        table(rows, path, "PCD row", columns=values)
    elif data == "binary":
        if points * row_bytes > file_size - offset:
            raise InputError(f"{path}: PCD header declares {points} points × {row_bytes} bytes = "
                             f"{points * row_bytes} bytes, only {file_size - offset} bytes follow byte offset {offset}")
    elif data == "binary_compressed":
        with open(path, "rb") as fh:
            fh.seek(offset)
            sizes = np.frombuffer(fh.read(8), dtype="<u4")
        if len(sizes) < 2 or sizes[1] != points * row_bytes or sizes[0] > file_size - offset - 8:
            raise InputError(f"{path}: PCD compressed block (byte offset {offset}) declares sizes {sizes.tolist()}; "
                             f"expected {points * row_bytes} bytes uncompressed and at most "
                             f"{file_size - offset - 8} compressed")
    else:
        raise InputError(f"{path}: PCD header DATA is {data!r} (ascii, binary or binary_compressed)")
    return points


def read_open3d(path: Path, expected: int | None) -> np.ndarray:
    """Points through Open3D; a count other than what the file declares means Open3D failed part-way."""
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    # NaN points are kept on purpose so that the engine reports them instead of silently dropping data.
    pcd = o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    pts = np.asarray(pcd.points, dtype=np.float64)
    if len(pts) == 0:
        raise InputError(f"{path}: no points read (the file is empty, truncated or not a point cloud)")
    if expected is not None and len(pts) != expected:
        raise InputError(f"{path}: the file declares {expected} points, Open3D read {len(pts)}")
    return pts


def read_point_file(path: Path) -> np.ndarray:
    """The (N,3) coordinates of a point file of any supported format, checked."""
    ext = path.suffix.lower()
    if ext == ".ply":
        return read_ply(path).vertices
    if ext in TEXT_COLUMNS:
        return read_xyz(path)
    if ext == ".pts":
        return read_pts(path)
    return read_open3d(path, check_pcd(path) if ext == ".pcd" else None)


class PointsParams(BaseModel):
    """Parameters of the Open3D point-cloud reader."""

    model_config = ConfigDict(extra="forbid")


def _accepts_points(path: Path, kind: str | None) -> bool:
    if kind == "mesh":
        return False
    if path.suffix.lower() == ".ply" and kind is None:
        # An unreadable header (None) is taken too, so that the error names what is wrong with it.
        return face_count(path) in (0, None)
    return True


def _read_points(req: ReadRequest) -> Dataset:
    return Dataset(name=req.name, role=req.role, points=read_point_file(req.path))


def _boxes(req: ReadRequest) -> Any:
    """A binary PLY point cloud opened for box reads, sorted by cell (scanners write scan order); other formats
    (text, PCD) have no way but reading them all."""
    if req.path.suffix.lower() != ".ply" or not read_header(req.path).endian:
        return None
    from .ply_boxes import PlyBoxes

    return PlyBoxes(req.path, sort_cells=True)


READER = ReaderSpec(name="open3d_points", version=VERSION, params=PointsParams, read=_read_points,
                    accepts=_accepts_points, boxes=_boxes,
                    extensions=(".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts"),
                    description="Point clouds: PLY and XYZ/XYZN/XYZRGB/PTS read and checked here, PCD through Open3D.")
