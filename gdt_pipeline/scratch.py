"""Scratch files: what a run keeps on disk instead of in memory (a file's points sorted by cell, the tiles'
candidates), in unnamed files under TMPDIR.

A scratch file has no name in its folder (``O_TMPFILE`` where the kernel has it), so whatever kills the run, the kernel
frees it with the last descriptor and nothing is left beside the twin. Rows go in with ``os.pwrite`` and come back with
``os.pread``, so the process holds one piece at a time, never a map of the whole file.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import IO

import numpy as np

from .errors import GdtError


def scratch_folder(folder: Path | None = None) -> Path:
    """The folder scratch files go to: ``folder``, else TMPDIR (the system's temporary folder)."""
    return Path(folder or tempfile.gettempdir())


def scratch_file(folder: Path, prefix: str) -> IO[bytes]:
    """A new scratch file in ``folder``, without a name there; the caller closes it."""
    return tempfile.TemporaryFile(prefix=prefix, dir=folder)


def write_at(file: IO[bytes], values: np.ndarray, offset: int, folder: Path, what: str, room: str) -> None:
    """``values``' bytes written at ``offset`` (short writes resumed); a full disk is named with the folder to change
    and ``room``, what the run needs there."""
    data = memoryview(np.ascontiguousarray(values).reshape(-1).view(np.uint8))
    try:
        while data:
            done = os.pwrite(file.fileno(), data, offset)
            data, offset = data[done:], offset + done
    except OSError as exc:
        raise GdtError(f"{folder}: writing {what} to scratch space failed ({exc.strerror}); set TMPDIR to a disk "
                       f"with room for {room}") from exc


def read_at(file: IO[bytes], dtype: np.dtype, shape: tuple[int, ...], offset: int) -> np.ndarray:
    """The array of ``dtype`` and ``shape`` stored at ``offset`` (short reads resumed; a file that ends first is an
    error, never rows of zeros)."""
    size = int(np.dtype(dtype).itemsize * np.prod(shape, dtype=np.int64))
    raw = os.pread(file.fileno(), size, offset)
    if len(raw) < size:
        parts = [raw]
        got = len(raw)
        while got < size:
            more = os.pread(file.fileno(), size - got, offset + got)
            if not more:
                raise GdtError(f"scratch file: {size} B asked at byte {offset}, the file ended after {got}")
            parts.append(more)
            got += len(more)
        raw = b"".join(parts)
    return np.frombuffer(raw, dtype=dtype).reshape(shape)


def reserved_map(folder: Path, prefix: str, dtype: type | np.dtype, shape: tuple[int, ...], what: str
                 ) -> tuple[IO[bytes], np.memmap]:
    """A scratch file reserved in full for an array of ``dtype`` and ``shape``, and its map for writing: a full disk
    is an error now, naming the folder, not a SIGBUS in the middle of a tile. The caller closes the file."""
    size = int(np.dtype(dtype).itemsize * np.prod(shape, dtype=np.int64))
    file = scratch_file(folder, prefix)
    try:
        os.posix_fallocate(file.fileno(), 0, max(size, 1))
    except OSError as exc:
        file.close()
        raise GdtError(f"{folder}: reserving {size / 1e9:.3g} GB of scratch space for {what} failed "
                       f"({exc.strerror}); set TMPDIR to a disk with room for it") from exc
    return file, np.memmap(file, dtype=dtype, mode="r+", shape=shape)
