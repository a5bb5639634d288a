"""PLY bodies read by hand against the header: every declared row present, every token a number, nothing left over.

Binary bodies are checked against the file length before anything is allocated (a header may promise 10⁹ vertices
in a 1 KB file); ASCII bodies are read line by line so an error names the line. Only the vertex and face elements
become data; the others are read (to find where the next element starts) and dropped.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gdt_pipeline import InputError

from .ply_header import Element, Header, Prop, read_header
from .text import Rows, check_integral, nonfinite, table, to_floats

_STRUCT = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "f4": "f", "f8": "d"}
FACE_LISTS = ("vertex_indices", "vertex_index")


@dataclass
class Polygons:
    """A list property: the items of all rows, flat, and each row's item count."""

    items: np.ndarray
    counts: np.ndarray


@dataclass
class ElementData:
    """What one element's rows hold, and where they are in the file (to name a bad row)."""

    element: Element
    fields: dict[str, np.ndarray | Polygons] = field(default_factory=dict)
    lines: list[int] | None = None
    offset: int = 0
    row_bytes: int = 0

    def place(self, row: int) -> str:
        """Where row ``row`` (0-based) of this element is in the file."""
        what = f"element {self.element.name!r} row {row + 1}"
        if self.lines is not None:
            return f"line {self.lines[row]} ({what})"
        return f"{what} (byte offset {self.offset + row * self.row_bytes})" if self.row_bytes else what


def row_dtype(props: list[Prop], endian: str, lists: dict[str, int]) -> np.dtype:
    """The numpy record type of a binary row (``lists``: each list property's item count)."""
    parts = []
    for p in props:
        if p.count_dtype is not None:
            parts.append((f"{p.name}__count", endian + p.count_dtype))
            parts.append((p.name, endian + p.dtype, (lists[p.name],)))
        else:
            parts.append((p.name, endian + p.dtype))
    return np.dtype(parts)


def _first_row_lists(data: np.ndarray, offset: int, el: Element, endian: str) -> dict[str, int] | None:
    """The list lengths of an element's first binary row (None when the row runs past the end of the file)."""
    lists, pos = {}, offset
    for p in el.props:
        width = int((p.count_dtype or p.dtype)[1])
        if pos + width > len(data):
            return None
        if p.count_dtype is None:
            pos += width
            continue
        n = int(data[pos:pos + width].view(endian + p.count_dtype)[0])
        lists[p.name] = n
        pos += width + n * int(p.dtype[1])
    return lists


def _uniform_rows(data: np.ndarray, offset: int, el: Element, endian: str) -> ElementData | None:
    """The rows of an element whose lists all have the first row's lengths (the usual triangle mesh), else None."""
    lists = {} if el.fixed else _first_row_lists(data, offset, el, endian)
    if lists is None:
        return None
    dt = row_dtype(el.props, endian, lists)
    need = el.count * dt.itemsize
    if need > len(data) - offset:
        return None
    rows = data[offset:offset + need].view(dt) if need else np.zeros(0, dt)
    out = ElementData(el, offset=offset, row_bytes=dt.itemsize)
    for p in el.props:
        if p.count_dtype is None:
            out.fields[p.name] = rows[p.name]
        elif (rows[f"{p.name}__count"] != lists[p.name]).any():
            return None
        else:
            out.fields[p.name] = Polygons(rows[p.name].reshape(-1), np.full(el.count, lists[p.name], np.int64))
    return out


def _rows_one_by_one(data: np.ndarray, offset: int, el: Element, endian: str) -> tuple[ElementData, int]:
    """Rows with lists of varying length, walked row by row; a row that runs past the end of the file is named."""
    raw, pos = data[offset:].tobytes(), 0
    scalars: dict[str, list] = {p.name: [] for p in el.props if p.count_dtype is None}
    items: dict[str, list] = {p.name: [] for p in el.props if p.count_dtype is not None}
    counts: dict[str, list] = {name: [] for name in items}
    for row in range(el.count):
        for p in el.props:
            width = int((p.count_dtype or p.dtype)[1])
            n = 0
            if p.count_dtype is not None and pos + width <= len(raw):
                n = struct.unpack_from(endian + _STRUCT[p.count_dtype], raw, pos)[0]
                pos += width
                width = n * int(p.dtype[1])
            if pos + width > len(raw):
                raise InputError(f"element {el.name!r} row {row + 1} of {el.count} (property {p.name!r}) runs past "
                                 f"the end of the file (byte offset {offset + pos}, file {offset + len(raw)} bytes)")
            values = struct.unpack_from(f"{endian}{n if p.count_dtype else 1}{_STRUCT[p.dtype]}", raw, pos)
            pos += width
            if p.count_dtype is None:
                scalars[p.name].append(values[0])
            else:
                items[p.name].extend(values)
                counts[p.name].append(n)
    out = ElementData(el, offset=offset)
    out.fields.update({k: np.asarray(v, dtype=el_dtype(el, k)) for k, v in scalars.items()})
    out.fields.update({k: Polygons(np.asarray(v, dtype=el_dtype(el, k)), np.asarray(counts[k], np.int64))
                       for k, v in items.items()})
    return out, pos


def el_dtype(el: Element, name: str) -> str:
    """The numpy type of property ``name`` of ``el``."""
    return next(p.dtype for p in el.props if p.name == name)


def _binary(path: Path, header: Header) -> list[ElementData]:
    data = np.memmap(path, dtype=np.uint8, mode="r")
    offset, out = header.body_offset, []
    for el in header.elements:
        remaining = len(data) - offset
        least = el.count * el.min_row_bytes()
        if least > remaining:
            kind = "" if el.fixed else "at least "
            raise InputError(f"{path}: element {el.name!r} declares {el.count} rows of {kind}{el.min_row_bytes()} "
                             f"bytes = {least} bytes, but only {remaining} bytes remain after byte offset {offset} "
                             f"(file {len(data)} bytes): truncated file or wrong header count")
        got = _uniform_rows(data, offset, el, header.endian)
        if got is not None:
            offset += el.count * got.row_bytes
        else:
            try:
                got, used = _rows_one_by_one(data, offset, el, header.endian)
            except InputError as exc:
                raise InputError(f"{path}: {exc}") from None
            offset += used
        out.append(got)
    if offset != len(data):
        raise InputError(f"{path}: {len(data) - offset} bytes after the last element (byte offset {offset}, file "
                         f"{len(data)} bytes): the header's counts do not describe the data")
    return out


def _ascii_lists(rows: Rows, el: Element, path: Path, what: str) -> ElementData:
    """An ASCII element with list properties: each row's token count must match its own list counts."""
    out = ElementData(el, lines=rows.numbers)
    per_row = [to_floats(rows.take(i, i + 1), path, what) for i in range(len(rows.lines))]
    parsed: dict[str, list] = {p.name: [] for p in el.props}
    counts: dict[str, list] = {p.name: [] for p in el.props if p.count_dtype is not None}
    for i, values in enumerate(per_row):
        col = 0
        for p in el.props:
            if col >= len(values):
                raise InputError(f"{path}: {out.place(i)}: {len(values)} values, property {p.name!r} missing")
            if p.count_dtype is None:
                parsed[p.name].append(values[col:col + 1])
                col += 1
                continue
            n = check_integral(values[col:col + 1], rows.take(i, i + 1), path, f"{what}, count of {p.name!r}")[0]
            if n < 0 or col + 1 + n > len(values):
                raise InputError(f"{path}: {out.place(i)}: list {p.name!r} says {n} items, the line has "
                                 f"{len(values) - col - 1} values after it")
            parsed[p.name].append(values[col + 1:col + 1 + n])
            counts[p.name].append(n)
            col += 1 + n
        if col != len(values):
            raise InputError(f"{path}: {out.place(i)}: {len(values) - col} values more than the properties declare")
    for p in el.props:
        flat = np.concatenate(parsed[p.name]) if parsed[p.name] else np.zeros(0)
        out.fields[p.name] = flat if p.count_dtype is None else Polygons(flat, np.asarray(counts[p.name], np.int64))
    return out


def _ascii_uniform(rows: Rows, el: Element, path: Path, what: str) -> ElementData | None:
    """An ASCII element whose rows all hold the same lists (the usual triangle mesh) as one matrix, else None."""
    widths = {len(line.split()) for line in rows.lines}
    if len(widths) != 1:
        return None
    mat = table(rows, path, what)
    out, col = ElementData(el, lines=rows.numbers), 0
    for p in el.props:
        if col >= mat.shape[1]:
            return None
        if p.count_dtype is None:
            out.fields[p.name] = mat[:, col]
            col += 1
            continue
        n = check_integral(mat[:, col], rows, path, f"{what}, count of {p.name!r}")
        if (n != n[0]).any() or n[0] < 0:
            return None
        out.fields[p.name] = Polygons(mat[:, col + 1:col + 1 + n[0]].reshape(-1), n)
        col += 1 + int(n[0])
    return out if col == mat.shape[1] else None


def _ascii_element(rows: Rows, el: Element, path: Path) -> ElementData:
    what = f"element {el.name!r}"
    if not el.fixed:
        return (_ascii_uniform(rows, el, path, what) if rows.lines else None) or _ascii_lists(rows, el, path, what)
    mat = table(rows, path, what, columns=len(el.props)) if rows.lines else np.zeros((0, len(el.props)))
    out = ElementData(el, lines=rows.numbers)
    out.fields.update({p.name: mat[:, i] for i, p in enumerate(el.props)})
    return out


def _ascii(path: Path, header: Header) -> list[ElementData]:
    with open(path, "rb") as fh:
        fh.seek(header.body_offset)
        rows = Rows.of(fh.read(), first_line=header.lines + 1)
    pos, out = 0, []
    for el in header.elements:
        if pos + el.count > len(rows.lines):
            end = rows.numbers[-1] if rows.lines else header.lines
            raise InputError(f"{path}: element {el.name!r} declares {el.count} rows, the file holds "
                             f"{len(rows.lines) - pos} (data ends at line {end})")
        out.append(_ascii_element(rows.take(pos, pos + el.count), el, path))
        pos += el.count
    if pos < len(rows.lines):
        raise InputError(f"{path}: line {rows.numbers[pos]}: {len(rows.lines) - pos} lines after the last element "
                         f"(the header declares {pos} rows in all)")
    return out


@dataclass
class PlyContent:
    """A checked PLY: the vertex coordinates (float64, finite) and the faces (indices in range), if any."""

    header: Header
    vertices: np.ndarray
    faces: Polygons | None


def _vertices(path: Path, data: ElementData) -> np.ndarray:
    names = [p.name for p in data.element.props]
    missing = [c for c in "xyz" if c not in names]
    if missing:
        raise InputError(f"{path}: element 'vertex' has no property {', '.join(missing)} (it has {names})")
    xyz = np.column_stack([np.asarray(data.fields[c], dtype=np.float64) for c in "xyz"]).reshape(-1, 3)
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        raise nonfinite(path, xyz, bad, data.place(first))
    return xyz


def _faces(path: Path, data: ElementData, n_vertices: int) -> Polygons:
    name = next((p.name for p in data.element.props if p.name in FACE_LISTS and p.count_dtype), None)
    if name is None:
        raise InputError(f"{path}: element 'face' (header line {data.element.line}) has no list property "
                         f"{' or '.join(FACE_LISTS)}")
    poly = data.fields[name]
    assert isinstance(poly, Polygons)
    if poly.items.dtype.kind == "f":  # ASCII: a float token where an index belongs is garbage, not index 1
        whole = np.isfinite(poly.items) & (poly.items == np.round(poly.items))
        if not whole.all():
            row = int(np.searchsorted(np.cumsum(poly.counts), int(np.argmax(~whole)), side="right"))
            raise InputError(f"{path}: {data.place(row)}: vertex index {poly.items[~whole][0]} is not an integer")
    short = poly.counts < 3
    if short.any():
        row = int(np.argmax(short))
        raise InputError(f"{path}: {data.place(row)}: a face needs at least 3 vertex indices, this one has "
                         f"{int(poly.counts[row])} ({int(short.sum())} such faces)")
    items = poly.items.astype(np.int64) if poly.items.dtype.kind != "f" else poly.items
    out = (items < 0) | (items >= n_vertices)
    if out.any():
        k = int(np.argmax(out))
        row = int(np.searchsorted(np.cumsum(poly.counts), k, side="right"))
        raise InputError(f"{path}: {data.place(row)}: vertex index {int(items[k])} is out of range "
                         f"[0, {n_vertices}) ({int(out.sum())} such indices)")
    return Polygons(items.astype(np.int64), poly.counts)


def read_ply(path: Path) -> PlyContent:
    """Read and check a whole PLY (header, every element's rows, finite vertices, face indices in range)."""
    header = read_header(path)
    if header.element("vertex") is None:
        raise InputError(f"{path}: the header declares no 'vertex' element")
    elements = _binary(path, header) if header.endian else _ascii(path, header)
    by_name = {d.element.name: d for d in elements}
    xyz = _vertices(path, by_name["vertex"])
    faces = _faces(path, by_name["face"], len(xyz)) if "face" in by_name else None
    return PlyContent(header, xyz, faces)
