"""STEP physical files (ISO 10303-21), the container of STEP CAD and IFC: checked whole before a parser sees them,
because both OpenCASCADE and IfcOpenShell read a file cut short without complaint and return what they got so far."""

from __future__ import annotations

from pathlib import Path

from gdt_pipeline import InputError

SPF_START, SPF_END = b"ISO-10303-21;", b"END-ISO-10303-21;"


def check_spf(path: Path, what: str = "IFC") -> None:
    """A STEP physical file (IFC, STEP CAD): it starts with ``ISO-10303-21;`` and ends with ``END-ISO-10303-21;``;
    an archive or XML variant is named as such."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(64)
        fh.seek(max(0, size - 256))
        tail = fh.read()
    head = head.removeprefix(b"\xef\xbb\xbf").lstrip()
    if head.startswith(b"PK\x03\x04"):
        raise InputError(f"{path}: a zip archive ({what}ZIP?): unzip it and give the file inside")
    if head.startswith(b"<"):
        raise InputError(f"{path}: XML ({what} XML?): only {what} STEP files (ISO-10303-21) are read")
    if not head.startswith(SPF_START):
        raise InputError(f"{path}: not a{'n' if what == 'IFC' else ''} {what} file: it does not start with "
                         f"'ISO-10303-21;' (STEP physical file)")
    if not tail.rstrip().endswith(SPF_END):
        raise InputError(f"{path}: truncated {what} file: it does not end with 'END-ISO-10303-21;' ({size} bytes)")
