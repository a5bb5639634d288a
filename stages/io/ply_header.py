"""The PLY header, parsed by hand: format, elements with their declared counts and properties.

Open3D and trimesh trust the header's counts (and Open3D returns a filled array when reading failed), so the readers
parse it themselves and check every declared size against the file before anything is allocated.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from gdt_pipeline import InputError

HEADER_LIMIT = 1 << 20  # a header longer than 1 MiB is not a PLY header
TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
         "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
         "double": "f8", "float64": "f8"}
FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
_END = re.compile(rb"(?:^|\n|\r)end_header[ \t]*(\r\n|\n|\r|$)")


@dataclass(frozen=True)
class Prop:
    """One property: ``dtype`` is the numpy type code; ``count_dtype`` is set for a list property."""

    name: str
    dtype: str
    count_dtype: str | None = None


@dataclass
class Element:
    """One element as the header declares it (``line`` is its 1-based header line)."""

    name: str
    count: int
    line: int
    props: list[Prop] = field(default_factory=list)

    @property
    def fixed(self) -> bool:
        """True when every row has the same byte size (no list property)."""
        return all(p.count_dtype is None for p in self.props)

    def min_row_bytes(self) -> int:
        """The smallest row a binary body can hold (lists empty)."""
        return sum(int(p.dtype[1]) if p.count_dtype is None else int(p.count_dtype[1]) for p in self.props)


@dataclass
class Header:
    """A parsed PLY header: ``endian`` is ``""`` for ASCII; the body starts at byte ``body_offset``."""

    fmt: str
    endian: str
    elements: list[Element]
    body_offset: int
    lines: int

    def element(self, name: str) -> Element | None:
        """The element called ``name`` (None when the header declares none)."""
        return next((e for e in self.elements if e.name == name), None)


def _head(path: Path) -> bytes:
    with open(path, "rb") as fh:
        head = fh.read(HEADER_LIMIT)
    if not head.startswith(b"ply"):
        raise InputError(f"{path}: not a PLY file (byte 0: the file does not start with 'ply')")
    return head


def _property(words: list[str], path: Path, number: int) -> Prop:
    where = f"{path}: header line {number}"
    if len(words) == 5 and words[1] == "list":
        count_t, item_t = TYPES.get(words[2]), TYPES.get(words[3])
        if count_t is None or item_t is None or count_t[0] == "f":
            raise InputError(f"{where}: list property {words[4]!r} has types {words[2]!r} {words[3]!r} "
                             f"(the count must be an integer type; types are {', '.join(TYPES)})")
        return Prop(words[4], item_t, count_t)
    if len(words) != 3 or words[1] not in TYPES:
        raise InputError(f"{where}: cannot read {' '.join(words)!r} (expected 'property <type> <name>' or "
                         f"'property list <count type> <item type> <name>')")
    return Prop(words[2], TYPES[words[1]])


def _format(words: list[str], path: Path, number: int) -> str:
    if len(words) != 3 or words[0] != "format" or words[1] not in FORMATS or words[2] not in ("1.0", "1"):
        raise InputError(f"{path}: header line {number}: expected 'format ascii|binary_little_endian|"
                         f"binary_big_endian 1.0', found {' '.join(words)!r}")
    return words[1]


def _element(words: list[str], path: Path, number: int) -> Element:
    if len(words) != 3 or not words[2].isdigit():
        raise InputError(f"{path}: header line {number}: expected 'element <name> <count>', found {' '.join(words)!r}")
    return Element(words[1], int(words[2]), number)


def read_header(path: Path) -> Header:
    """Parse the header of the PLY at ``path``, or raise an error naming the header line that is wrong."""
    head = _head(path)
    end = _END.search(head)
    if end is None:
        got = "the first 1 MiB" if len(head) == HEADER_LIMIT else f"the whole file ({len(head)} bytes)"
        raise InputError(f"{path}: no 'end_header' line in {got}: not a PLY file or a truncated header")
    try:
        text = head[:end.start()].decode("ascii")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: byte {exc.start} of the header is not ASCII text") from None
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    fmt, elements = "", []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if not fmt:
            fmt = _format(words, path, number)
        elif words[0] == "element":
            elements.append(_element(words, path, number))
        elif words[0] == "property" and elements:
            elements[-1].props.append(_property(words, path, number))
        else:
            raise InputError(f"{path}: header line {number}: unexpected {line.strip()[:60]!r}")
    if not fmt:
        raise InputError(f"{path}: the header has no 'format' line")
    empty = next((e for e in elements if not e.props and e.count), None)
    if empty is not None:
        raise InputError(f"{path}: header line {empty.line}: element {empty.name!r} has {empty.count} rows but no "
                         f"properties")
    return Header(fmt, FORMATS[fmt], elements, end.end(), len(lines) + 1)


def face_count(path: Path) -> int | None:
    """Number of faces the PLY header declares (None when the header cannot be read)."""
    try:
        header = read_header(path)
    except (InputError, OSError):
        return None
    face = header.element("face")
    return face.count if face is not None else 0
