"""Giving freed memory back to the system between the phases of a run, so that its peak is what it holds.

glibc's malloc serves arrays below its mmap threshold (which rises to 32 MB once such a block is freed) from the
heap, and keeps the heap's freed pages. A tile's results are arrays of that size: once merged and let go, their
pages stay resident, and the merged arrays, above the threshold, come on top. ``malloc_trim`` hands them back. There
is no Python or numpy call for it, hence ctypes; elsewhere than glibc this does nothing.

Pages of a scratch file mapped into the process (the scans' covariances kept on disk, ``tiling.RecentSink``) count in
its resident set once touched, though the kernel could drop them: they are let go of too (``MADV_DONTNEED``; they stay
in the page cache, and a later read maps them again).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import mmap
import resource
import weakref
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


# the scratch-file maps alive, whose pages ``return_freed_memory`` lets go of (weak: a map no one holds is closed)
_SCRATCH_MAPS: weakref.WeakSet[mmap.mmap] = weakref.WeakSet()


def track_scratch_map(pages: mmap.mmap) -> None:
    """Have ``return_freed_memory`` let go of this scratch-file map's resident pages too."""
    _SCRATCH_MAPS.add(pages)


def release_pages(pages: mmap.mmap) -> None:
    """Let go of a file map's resident pages (they stay in the page cache; a closed map has none)."""
    with contextlib.suppress(ValueError, OSError):
        pages.madvise(mmap.MADV_DONTNEED)


def release_scratch_pages() -> None:
    """Let go of the resident pages of every live scratch-file map (a pass that read rows of them at random holds
    the pages around those rows: a whole scan's covariances at the region of view's end, 3.7 GB at 50 M points)."""
    for pages in list(_SCRATCH_MAPS):
        release_pages(pages)


def return_freed_memory() -> None:
    """Hand the heap's free pages back to the system (glibc only; a few milliseconds), and the scratch-file maps'."""
    trim = _trim()
    if trim is not None:
        trim(0)
    release_scratch_pages()


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
