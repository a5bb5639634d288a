"""Giving freed memory back to the system between the phases of a run, so that its peak is what it holds.

glibc's malloc serves arrays below its mmap threshold (which rises to 32 MB once such a block is freed) from the
heap, and keeps the heap's freed pages. A tile's results are arrays of that size: once merged and let go, their
pages stay resident, and the merged arrays, above the threshold, come on top. ``malloc_trim`` hands them back. There
is no Python or numpy call for it, hence ctypes; elsewhere than glibc this does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable


@functools.cache
def _trim() -> Callable[[int], int] | None:
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
    except OSError:
        return None
    return getattr(libc, "malloc_trim", None)


def return_freed_memory() -> None:
    """Hand the heap's free pages back to the system (glibc only; a few milliseconds)."""
    trim = _trim()
    if trim is not None:
        trim(0)
