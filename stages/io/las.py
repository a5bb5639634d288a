"""LAS/LAZ through laspy, with the header checked first: laspy allocates what the header's point count asks for, so
a few bytes of garbage after a ``LASF`` signature once took gigabytes and minutes before failing.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any, BinaryIO, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gdt_pipeline import Dataset, InputError, ReaderSpec, ReadRequest

from .version import VERSION

# LAZ compresses point records about 5-10×; more than this many records per file byte cannot be real.
LAZ_MAX_RATIO = 64
# The shortest record of each point format 0-10 (ASPRS LAS 1.4 R15, table of point data record formats).
_MIN_RECORD = (20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67)
_VLR_HEADER, _EVLR_HEADER = 54, 60


# Points read at a time (about 70 MB of point records in the common formats).
CHUNK_POINTS = 2_000_000


def failure(path: Path, what: str, exc: BaseException) -> InputError:
    """laspy's failure as an error naming the file; lazrs (Rust) reports a panic as pyo3's PanicException, a
    BaseException that ``except Exception`` misses, so it is caught here and anything else non-Exception re-raised."""
    if not isinstance(exc, Exception) and type(exc).__name__ != "PanicException":
        raise exc
    return InputError(f"{path}: cannot read {what} ({type(exc).__name__}: {str(exc)[:200]})")


def _field(data: bytes, fmt: str, offset: int) -> int | float:
    return struct.unpack_from("<" + fmt, data, offset)[0]


def _check_public_header(path: Path, data: bytes, size: int) -> None:
    """The public header block's fields that decide what laspy allocates, checked before laspy sees the file.

    laspy trusts the VLR and EVLR counts and offsets: a garbage header after a valid ``LASF`` signature once made
    ``laspy.open`` take 60 s and gigabytes before failing, so each is bounded by the bytes that can hold it.
    """
    if len(data) < 227 or data[:4] != b"LASF":
        raise InputError(f"{path}: not a LAS file ({size} bytes; a LAS header is 227+ bytes starting 'LASF')")
    major, minor = data[24], data[25]
    header_size, offset, n_vlrs = _field(data, "H", 94), _field(data, "I", 96), _field(data, "I", 100)
    if major != 1 or minor > 4:
        raise InputError(f"{path}: LAS header (byte 24) version {major}.{minor} (expected 1.0-1.4)")
    if not 227 <= header_size <= offset <= size:
        raise InputError(f"{path}: LAS header size (byte 94) {header_size} and offset to point data (byte 96) "
                         f"{offset} do not fit a {size}-byte file")
    if n_vlrs * _VLR_HEADER > offset - header_size:
        raise InputError(f"{path}: LAS header (byte 100) declares {n_vlrs} VLRs, at least {n_vlrs * _VLR_HEADER} "
                         f"bytes, but only {offset - header_size} bytes lie between the header and the points")
    fmt_id, record = data[104] & 0x3F, _field(data, "H", 105)
    if fmt_id > 10 or record < _MIN_RECORD[fmt_id]:
        raise InputError(f"{path}: LAS header (byte 104) point format {fmt_id} with {record}-byte records is not "
                         f"a LAS point format (0-10, record at least the format's size)")
    if minor >= 4 and len(data) >= 247:
        start, n_evlrs = _field(data, "Q", 235), _field(data, "I", 243)
        if n_evlrs and (start > size or n_evlrs * _EVLR_HEADER > size - start):
            raise InputError(f"{path}: LAS header (byte 235) declares {n_evlrs} EVLRs from byte {start}, the file "
                             f"is {size} bytes")


def las_header(path: Path) -> Any:  # laspy.LasHeader, imported lazily
    """The file's header as laspy reads it (its failure named as the file's)."""
    import laspy

    try:
        with laspy.open(str(path)) as reader:
            return reader.header
    except BaseException as exc:  # lazrs panics are BaseExceptions: see failure
        raise failure(path, "the LAS/LAZ header", exc) from exc


def laszip_vlr(data: bytes, n_vlrs: int) -> bytes | None:
    """The LASzip VLR's payload among the VLRs ``data`` holds (None when there is none)."""
    pos = 0
    for _ in range(n_vlrs):
        if pos + _VLR_HEADER > len(data):
            return None
        length = _field(data, "H", pos + 20)
        if data[pos + 2:pos + 16] == b"laszip encoded" and _field(data, "H", pos + 18) == 22204:
            return data[pos + _VLR_HEADER:pos + _VLR_HEADER + length]
        pos += _VLR_HEADER + length
    return None


def _check_laz(path: Path, fh: BinaryIO, count: int, size: int) -> None:
    """The LASzip items and chunk table, bounded by the file: lazrs allocates what they declare and aborts the
    process (not an exception) when that fails, so a flipped byte there would end the run."""
    header = fh.read(375)
    header_size, offset, n_vlrs, record = (_field(header, "H", 94), _field(header, "I", 96),
                                           _field(header, "I", 100), _field(header, "H", 105))
    fh.seek(header_size)
    vlr = laszip_vlr(fh.read(offset - header_size), n_vlrs)
    if vlr is None or len(vlr) < 34 or len(vlr) < 34 + 6 * _field(vlr, "H", 32):
        raise InputError(f"{path}: compressed points but no readable LASzip VLR (bytes {header_size}-{offset})")
    n_items = _field(vlr, "H", 32)
    item_bytes = sum(_field(vlr, "H", 34 + 6 * k + 2) for k in range(n_items))
    if item_bytes != record:
        raise InputError(f"{path}: LASzip VLR items ({n_items}) add up to {item_bytes} bytes, the header's point "
                         f"records are {record} bytes")
    chunk_size = _field(vlr, "I", 12)
    if chunk_size != 0xFFFFFFFF and chunk_size * record > max(LAZ_MAX_RATIO * size, 1 << 24):
        raise InputError(f"{path}: LASzip VLR (byte {header_size + _VLR_HEADER + 12}) declares chunks of {chunk_size} "
                         f"points × {record} bytes, more than a {size}-byte file can hold")
    fh.seek(offset)
    table_at = _field(fh.read(8).ljust(8, b"\xff"), "q", 0)
    if table_at == -1:
        return  # no chunk table written: lazrs reads the chunks sequentially
    fh.seek(table_at if 0 <= table_at <= size - 8 else 0)
    version, chunks = struct.unpack("<II", fh.read(8)) if 0 <= table_at <= size - 8 else (0, 0)
    if not offset + 8 <= table_at <= size - 8 or version != 0 or chunks > min(count + 1, size):
        raise InputError(f"{path}: LAZ chunk table (offset at byte {offset}) at byte {table_at} declares version "
                         f"{version} and {chunks} chunks, for {count} points in a {size}-byte file")


def check_las_header(path: Path) -> int:
    """The point count the header declares, checked against the file size (and the scales usable)."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        _check_public_header(path, fh.read(375), size)
    header = las_header(path)
    count, record = int(header.point_count), int(header.point_format.size)
    offset = int(header.offset_to_point_data)
    scales = np.asarray(header.scales, dtype=np.float64)
    if not (np.isfinite(scales).all() and (scales != 0).all()) or not np.isfinite(header.offsets).all():
        raise InputError(f"{path}: LAS header scale {scales.tolist()} / offset {list(header.offsets)} is not usable "
                         f"(zero or not finite)")
    compressed = bool(getattr(header, "are_points_compressed", False)) or path.suffix.lower() == ".laz"
    if not compressed and offset + count * record > size:
        raise InputError(f"{path}: LAS header declares {count} points × {record} bytes + {offset} bytes offset to the "
                         f"point data = {offset + count * record} bytes, but the file is {size} bytes")
    if compressed and count > LAZ_MAX_RATIO * size / max(record, 1):
        raise InputError(f"{path}: LAZ header declares {count} points of {record} bytes in a {size}-byte file (more "
                         f"than {LAZ_MAX_RATIO}× compression is impossible): corrupt header")
    if compressed:
        with open(path, "rb") as fh:
            _check_laz(path, fh, count, size)
    return count


def read_las_points(path: Path, classes: list[int] | None) -> np.ndarray:
    """(N,3) scaled coordinates of a LAS/LAZ (optionally only some ASPRS classes): :func:`read_las` without the
    per-point attributes."""
    return read_las(path, classes, ())[0]


def colour_scale(top: int) -> float:
    """LAS stores RGB as 16-bit, but many writers put 8-bit values there: a file whose channels all stay within
    0..255 is read as 8-bit (the convention CloudCompare and PDAL follow too). Decided for the whole file, so that a
    dark first part of a scan is not read on another scale than the rest, and a tile the same as the whole read."""
    return 255.0 if top <= 255 else 65535.0


def attribute_rows(chunk: Any, keep: Any, attributes: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The attributes asked for that a chunk's point format has: intensity as float32, colour as the file's uint16
    (scaled once the file's largest value is known: :func:`scaled_colour`), the ASPRS classification as uint8
    (every point format has one)."""
    names = set(chunk.point_format.dimension_names)
    out: dict[str, np.ndarray] = {}
    if "classification" in attributes and "classification" in names:
        out["classification"] = np.asarray(chunk.classification, dtype=np.uint8)[keep]
    if "intensity" in attributes and "intensity" in names:
        out["intensity"] = np.asarray(chunk.intensity, dtype=np.float32)[keep]
    if "color" in attributes and {"red", "green", "blue"} <= names:
        out["color"] = np.column_stack([np.asarray(chunk.red), np.asarray(chunk.green), np.asarray(chunk.blue)])[keep]
    return out


def scaled_colour(fields: dict[str, np.ndarray], top: int) -> dict[str, np.ndarray]:
    """``fields`` with the raw colour as float32 0..1 on the scale of a file whose largest channel value is ``top``."""
    if "color" in fields:
        fields["color"] = (fields["color"] / colour_scale(top)).astype(np.float32)
    return fields


def read_las(path: Path, classes: list[int] | None, attributes: tuple[str, ...] = ("intensity", "color")
             ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(N,3) scaled coordinates of a LAS/LAZ (optionally only some ASPRS classes) and the per-point ``attributes``
    the point format has (``intensity``, ``color``, ``classification``), header checked first; read a chunk of
    points at a time, so that reading costs what it returns (24 bytes a point, plus 4 for intensity, 12 for colour
    and 1 for the class), not the whole point records and their copies besides (about 100 bytes a point)."""
    import laspy

    count = check_las_header(path)
    pts = np.empty((count, 3))
    fields: dict[str, list[np.ndarray]] = {}
    filled = read = 0
    try:
        with laspy.open(str(path)) as reader:  # LAZ chunks on every core: laspy's default backend
            for chunk in reader.chunk_iterator(CHUNK_POINTS):
                n = len(chunk)
                if read + n > count:
                    raise InputError(f"{path}: the LAS header declares {count} points, but the file holds more")
                keep = slice(None) if classes is None else np.isin(np.asarray(chunk.classification), classes)
                rows = pts[filled:filled + (n if classes is None else int(np.count_nonzero(keep)))]
                for axis, values in enumerate((chunk.x, chunk.y, chunk.z)):
                    rows[:, axis] = np.asarray(values)[keep]
                for name, values in attribute_rows(chunk, keep, attributes).items():
                    fields.setdefault(name, []).append(values)
                filled += len(rows)
                read += n
    except InputError:
        raise
    except BaseException as exc:  # lazrs panics are BaseExceptions: see failure
        raise failure(path, "LAS/LAZ", exc) from exc
    if read != count:
        raise InputError(f"{path}: the LAS header declares {count} points, laspy read {read}")
    merged = {name: np.concatenate(parts) for name, parts in fields.items()}
    return pts[:filled], scaled_colour(merged, int(np.max(merged["color"], initial=0)) if "color" in merged else 0)


class LasParams(BaseModel):
    """Parameters of the laspy LAS/LAZ reader."""

    model_config = ConfigDict(extra="forbid")
    classes: list[int] | None = Field(None, description="Keep only points of these ASPRS classes (e.g. [2] ground).")
    attributes: list[Literal["intensity", "color", "classification"]] = Field(
        ["intensity", "color", "classification"],
        description="Per-point values to keep when the file has them: intensity and color go into the twin "
                    "(gdt:intensity, gdt:scanColor), classification is what a registrar's `classes` selects; [] for "
                    "coordinates only.")


def _read_las(req: ReadRequest) -> Dataset:
    pts, fields = read_las(req.path, req.params.classes, tuple(req.params.attributes))
    if len(pts) == 0:
        raise InputError(f"{req.path}: no points (after the class filter {req.params.classes})")
    return Dataset(name=req.name, role=req.role, points=pts, fields=fields)


def _boxes(req: ReadRequest) -> Any:  # las_boxes imports this module
    from .las_boxes import las_boxes

    return las_boxes(req)


READER = ReaderSpec(name="laspy_points", version=VERSION, params=LasParams, read=_read_las, extensions=(".las", ".laz"),
                    boxes=_boxes,
                    description="LAS/LAZ LiDAR point clouds (and COPC) through laspy (lazrs backend); reads a box at "
                                "a time through a first-pass index, or a COPC file's octree.")
