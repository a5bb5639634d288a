"""Read-only, shape-checked numpy arrays: what every record below holds."""

from __future__ import annotations

from typing import Any

import numpy as np


def frozen_array(a: np.ndarray | list[Any] | tuple[Any, ...], dtype: type | np.dtype[Any],
                 ndim_shape: tuple[int | None, ...], what: str) -> np.ndarray:
    """Return a read-only C-contiguous copy of ``a`` with the given dtype, checking its shape (None = any)."""
    arr = np.ascontiguousarray(np.asarray(a, dtype=dtype))
    if arr.ndim != len(ndim_shape) or any(s is not None and s != d for s, d in zip(ndim_shape, arr.shape, strict=True)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in ndim_shape) + ")"
        raise ValueError(f"{what}: expected shape {want}, got {arr.shape}")
    if arr is a or arr.base is not None:
        arr = arr.copy()
    arr.setflags(write=False)
    return arr


def broadcast_rows(arr: np.ndarray, n: int, what: str) -> None:
    """Check that a per-element array has one row, to broadcast, or one row per element."""
    if arr.shape[0] not in (1, n):
        raise ValueError(f"{what}: {arr.shape[0]} rows for {n} elements (give 1 to broadcast, or one per element)")


# The twin's order of a symmetric 3x3 matrix's six distinct entries: xx xy xz yy yz zz (``gdt:covariance``).
_UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def covariance6(cov: np.ndarray) -> np.ndarray:
    """``(N,3,3)`` symmetric matrices packed as ``(N,6)`` in the twin's order xx xy xz yy yz zz."""
    return cov[:, _UPPER[0], _UPPER[1]]


def covariance33(cov6: np.ndarray) -> np.ndarray:
    """The inverse of ``covariance6``: ``(N,6)`` packed rows as symmetric ``(N,3,3)`` float64 matrices."""
    cov = np.empty((len(cov6), 3, 3))
    cov[:, _UPPER[0], _UPPER[1]] = cov6
    cov[:, _UPPER[1], _UPPER[0]] = cov6
    return cov
