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
import resource
from collections.abc import Callable
from pathlib import Path


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


def peak_rss_mb() -> float:
    """This process's peak resident set in MB: VmHWM, which restarts at ``exec`` (``ru_maxrss`` carries the peak of
    the process that forked this one, such as a large test or bench process, across it)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
