"""The writer lock of a twin: one writer at a time, and a second one is told who holds the twin."""

from __future__ import annotations

import contextlib
import fcntl
import os
import time
from collections.abc import Iterator
from pathlib import Path

from .errors import TwinStoreError


def lock_path(twin: Path) -> Path:
    """The writer lock of a twin: a file beside the twin folder (the folder itself may be swapped whole)."""
    twin = Path(twin).resolve()
    return twin.parent / f".{twin.name}.lock"


@contextlib.contextmanager
def writer_lock(twin: str | Path) -> Iterator[None]:
    """Hold the twin's writer lock; a second writer gets a clear TwinStoreError instead of waiting or corrupting."""
    path = lock_path(Path(twin))
    path.parent.mkdir(parents=True, exist_ok=True)
    fh = open(path, "a+", encoding="utf-8")  # noqa: SIM115  (closed in finally; flock needs the open file)
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "unknown process"
            raise TwinStoreError(f"twin {Path(twin).resolve()} is being written by another writer ({holder}); "
                                 f"wait for it to finish (lock: {path})") from None
        try:
            fh.seek(0)
            fh.truncate()
            fh.write(f"pid {os.getpid()} since {time.strftime('%Y-%m-%dT%H:%M:%S')}")
            fh.flush()
            yield
        finally:
            # only the holder clears the record: a refused writer must leave the holder's pid for the next one
            with contextlib.suppress(OSError):
                fh.truncate(0)
    finally:
        fh.close()  # closing releases the flock
