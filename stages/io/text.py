"""Numbers from text files, checked: every token must parse as a number and the reader is told the line it came from.

Python's and numpy's float parsers accept more than a number (``1_000``), and C's ``sscanf`` that Open3D uses skips
or zero-fills what it cannot parse, so the text readers check the tokens themselves before anything becomes data.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from gdt_pipeline import InputError

# A number token holds only these characters (letters for inf/nan/infinity); anything else is garbage. The finer
# check (``1.2.3``, ``e``) is the float parser's.
MAX_TOKEN = 64  # characters: no number a writer prints is longer
_NOT_NUMERIC = re.compile(rb"[^0-9eE+\-.\sinfatyINFATY]")


@dataclass(frozen=True)
class Rows:
    """Non-blank lines of a text block with their 1-based line numbers in the file."""

    lines: list[bytes]
    numbers: list[int]

    @classmethod
    def of(cls, text: bytes, first_line: int = 1) -> Rows:
        """The non-blank lines of ``text``, numbered from ``first_line``."""
        lines, numbers = [], []
        for i, line in enumerate(text.split(b"\n")):
            if line.strip():
                lines.append(line)
                numbers.append(first_line + i)
        return cls(lines, numbers)

    def take(self, start: int, stop: int) -> Rows:
        """Rows ``start`` to ``stop`` (indices into the non-blank lines)."""
        return Rows(self.lines[start:stop], self.numbers[start:stop])


def _bad_token(rows: Rows, path: object, what: str) -> InputError:
    """The first token of ``rows`` that is not a number, as an error naming its line."""
    for line, number in zip(rows.lines, rows.numbers, strict=True):
        for tok in line.split():
            try:
                if _NOT_NUMERIC.search(tok):
                    raise ValueError(tok)
                float(tok)
            except ValueError:
                shown = tok[:40].decode("latin-1")
                return InputError(f"{path}: line {number} ({what}): {shown!r} is not a number")
    return InputError(f"{path}: {what}: a token is not a number")


def to_floats(rows: Rows, path: object, what: str) -> np.ndarray:
    """All tokens of ``rows`` as float64 (flat), or an error naming the line and the token that is not a number."""
    block = b" ".join(rows.lines)
    if _NOT_NUMERIC.search(block):
        raise _bad_token(rows, path, what)
    tokens = block.split()
    # numpy sizes a bytes array by its longest token: one 5 MB token among a million would ask for terabytes.
    longest = max(map(len, tokens), default=0)
    if longest > MAX_TOKEN:
        k = next(i for i, t in enumerate(tokens) if len(t) == longest)
        line = next(n for line, n in zip(rows.lines, rows.numbers, strict=True) if tokens[k] in line)
        raise InputError(f"{path}: line {line} ({what}): a token of {longest} characters is not a number")
    try:
        return np.array(tokens).astype(np.float64) if tokens else np.zeros(0)
    except ValueError:
        raise _bad_token(rows, path, what) from None


def table(rows: Rows, path: object, what: str, *, columns: int | None = None, min_columns: int = 1) -> np.ndarray:
    """Rows of the same token count as a float64 matrix; a row with another count is named by its line."""
    counts = [len(line.split()) for line in rows.lines]
    width = columns if columns is not None else (counts[0] if counts else min_columns)
    if width < min_columns:
        raise InputError(f"{path}: line {rows.numbers[0]} ({what}): {width} values, at least {min_columns} needed")
    for count, number in zip(counts, rows.numbers, strict=True):
        if count != width:
            raise InputError(f"{path}: line {number} ({what}): expected {width} values, found {count}")
    return to_floats(rows, path, what).reshape(len(rows.lines), width)


def nonfinite(path: object, xyz: np.ndarray, bad: np.ndarray, place: str) -> InputError:
    """The error for rows with NaN/inf coordinates: how many, the first rows (from 0, as the engine counts) and
    where the first one is in the file."""
    first = np.flatnonzero(bad)[:5].tolist()
    return InputError(f"{path}: {int(bad.sum())} of {len(xyz)} coordinates are NaN or infinite (first rows {first}, "
                      f"counting from 0); the first is at {place}: {xyz[first[0]].tolist()}")


def check_finite(xyz: np.ndarray, rows: Rows, path: object, what: str) -> None:
    """Refuse NaN/inf coordinates, naming the first bad row's line."""
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        raise nonfinite(path, xyz, bad, f"line {rows.numbers[first]} ({what} {first + 1})")


def check_integral(values: np.ndarray, rows: Rows, path: object, what: str) -> np.ndarray:
    """Values that must be integers (counts, indices) as int64, or an error naming the first line that is not."""
    ok = np.isfinite(values) & (values == np.round(values)) & (np.abs(values) < 2**62)
    if not ok.all():
        first = int(np.argmax(~ok.reshape(len(values), -1).all(axis=1))) if values.ndim > 1 else int(np.argmax(~ok))
        raise InputError(f"{path}: line {rows.numbers[first]} ({what}): {values[first].tolist()} is not an integer")
    return values.astype(np.int64)
