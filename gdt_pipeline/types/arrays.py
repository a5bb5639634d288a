"""Read-only, shape-checked numpy arrays: what every record below holds; and rows kept in a scratch file
(``MappedRows``), which the records hold as they are."""

from __future__ import annotations

import mmap
from collections.abc import Callable
from typing import Any, Self, cast

import numpy as np

from ..memory import release_pages, track_scratch_map

# Rows a ``MappedRows`` gathers before it lets go of the file pages it touched: random rows touch a page each, so
# this bounds the pages mapped at once (32 MB) whatever the number of rows taken.
MAPPED_PIECE = 8192
# Rows a pass over all of a ``MappedRows`` (``by_pieces``) reads before it lets go of their pages: 18 MB of covariances.
PASS_PIECE = 1 << 18


class MappedRows(np.memmap):
    """A read-only array over a scratch file (``np.memmap``) whose rows are taken a piece at a time: after each piece
    the pages it touched leave the process (``MADV_DONTNEED``; they stay in the page cache), so a process that takes
    a hundred thousand random rows of a 10⁸-row file holds those rows, not the pages around them. Its map is one
    ``memory.return_freed_memory`` lets go of between stages."""

    def __new__(cls, *args: Any, **kwargs: Any) -> Self:
        rows = cast(Self, super().__new__(cls, *args, **kwargs))  # np.memmap's stubs say it makes a memmap
        pages = getattr(rows, "_mmap", None)
        if pages is not None:
            track_scratch_map(pages)
        return rows

    def __getitem__(self, index: Any) -> Any:
        rows = _row_selection(index, self.shape[0] if self.ndim else 0)
        pages: mmap.mmap | None = getattr(self, "_mmap", None)  # np.memmap's map (None for a copy)
        if rows is None or pages is None:
            return super().__getitem__(index)
        out = np.empty((len(rows), *self.shape[1:]), dtype=self.dtype)
        plain = self.view(np.ndarray)
        for start in range(0, len(rows), MAPPED_PIECE):
            out[start:start + MAPPED_PIECE] = plain[rows[start:start + MAPPED_PIECE]]
            pages.madvise(mmap.MADV_DONTNEED)
        return out


def index_dtype(n: int) -> type[np.signedinteger[Any]]:
    """The narrowest of int32 and int64 that indexes ``n`` rows: index arrays over an epoch's points take 4 B a
    point instead of 8 (half a gigabyte each at 10⁸ points)."""
    return np.int32 if n < np.iinfo(np.int32).max else np.int64


def index_column(values: Any) -> type[np.signedinteger[Any]]:
    """The dtype a per-candidate index column is held in: int32 when its values fit (an int32 column stays one
    without a pass over it), else int64. The narrow columns are what a run keeps of every candidate: 16 B a
    candidate less at four columns, 1.4 GB at 50 M points."""
    if isinstance(values, np.ndarray) and values.dtype == np.int32:
        return np.int32
    values = np.asarray(values)
    if values.size == 0 or values.dtype.kind == "b":
        return np.int32
    limits = np.iinfo(np.int32)
    return np.int32 if limits.min <= values.min() and values.max() <= limits.max else np.int64


def by_pieces(rows: np.ndarray, per_rows: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """``per_rows`` of every row, row for row; over a ``MappedRows``, ``PASS_PIECE`` rows at a time, letting go of the
    pages each piece read, so that a pass over a scratch file leaves the process holding the result, not the file."""
    pages = getattr(rows, "_mmap", None) if isinstance(rows, MappedRows) else None
    if pages is None:
        return per_rows(rows)
    plain = rows.view(np.ndarray)
    out: np.ndarray | None = None
    for start in range(0, max(len(plain), 1), PASS_PIECE):
        part = per_rows(plain[start:start + PASS_PIECE])
        if out is None:
            out = np.empty((len(plain), *part.shape[1:]), dtype=part.dtype)
        out[start:start + len(part)] = part
        release_pages(pages)
    assert out is not None
    return out


def rows_copy(rows: np.ndarray, start: int, stop: int) -> np.ndarray:
    """Rows [start, stop) as an array of their own; of a ``MappedRows``, the pages read are let go after the copy."""
    out = np.array(rows[start:stop])
    pages = getattr(rows, "_mmap", None) if isinstance(rows, MappedRows) else None
    if pages is not None:
        release_pages(pages)
    return out


def _row_selection(index: Any, n: int) -> np.ndarray | None:
    """The rows a first-axis selection by an integer or boolean array takes (None for any other index)."""
    if not isinstance(index, np.ndarray) or index.ndim != 1:
        return None
    if index.dtype == bool:
        return np.flatnonzero(index) if len(index) == n else None
    return index if index.dtype.kind in "iu" else None


def _shared_as_is(a: MappedRows, dtype: type | np.dtype[Any]) -> bool:
    """Whether rows of a scratch-file map are held as they are: read-only (nobody can write them) and of ``dtype``."""
    return not a.flags.writeable and a.flags.c_contiguous and a.dtype == np.dtype(dtype)


def frozen_array(a: np.ndarray | list[Any] | tuple[Any, ...], dtype: type | np.dtype[Any],
                 ndim_shape: tuple[int | None, ...], what: str) -> np.ndarray:
    """Return a read-only C-contiguous copy of ``a`` with the given dtype, checking its shape (None = any). Held as
    they are: a ``MappedRows`` of that dtype (read-only by construction, and copying it is what it avoids), and an
    array this function already froze (a dataset rebuilt with its uncertainty would copy its points again)."""
    shared = (isinstance(a, MappedRows) and _shared_as_is(a, dtype)) or _frozen_already(a, dtype)
    arr = a if shared and isinstance(a, np.ndarray) else np.ascontiguousarray(np.asarray(a, dtype=dtype))
    if arr.ndim != len(ndim_shape) or any(s is not None and s != d for s, d in zip(ndim_shape, arr.shape, strict=True)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in ndim_shape) + ")"
        raise ValueError(f"{what}: expected shape {want}, got {arr.shape}")
    if shared:
        return arr
    if arr is a or arr.base is not None:
        arr = arr.copy()
    arr.setflags(write=False)
    return arr


def _frozen_already(a: object, dtype: type | np.dtype[Any]) -> bool:
    """Whether ``a`` is an array no one can write through: read-only, owning its memory, of ``dtype``, C-contiguous
    (what ``frozen_array`` returns; a read-only view could still be written through its base)."""
    if not isinstance(a, np.ndarray) or type(a) is not np.ndarray:
        return False
    return not a.flags.writeable and a.base is None and a.flags.c_contiguous and a.dtype == np.dtype(dtype)


def broadcast_rows(arr: np.ndarray, n: int, what: str) -> None:
    """Check that a per-element array has one row, to broadcast, or one row per element."""
    if arr.shape[0] not in (1, n):
        raise ValueError(f"{what}: {arr.shape[0]} rows for {n} elements (give 1 to broadcast, or one per element)")


# The twin's order of a symmetric 3x3 matrix's six distinct entries: xx xy xz yy yz zz (``gdt:covariance``).
_UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def covariance6(cov: np.ndarray) -> np.ndarray:
    """``(N,3,3)`` symmetric matrices packed as ``(N,6)`` in the twin's order xx xy xz yy yz zz."""
    return by_pieces(cov, lambda rows: rows[:, _UPPER[0], _UPPER[1]])


def covariance33(cov6: np.ndarray) -> np.ndarray:
    """The inverse of ``covariance6``: ``(N,6)`` packed rows as symmetric ``(N,3,3)`` float64 matrices."""
    cov = np.empty((len(cov6), 3, 3))
    cov[:, _UPPER[0], _UPPER[1]] = cov6
    cov[:, _UPPER[1], _UPPER[0]] = cov6
    return cov
