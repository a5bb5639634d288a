"""Building a twin beside its target and moving it into place only when complete."""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path
from typing import Any

log = logging.getLogger("gdt.run")


def staging_path(target: Path) -> Path:
    """Where this process builds the twin before it moves it to ``target``."""
    return target.parent / f".{target.name}.partial-{os.getpid()}"


def remove_stale_staging(target: Path) -> None:
    """Remove partial twins of runs that were killed (their process is gone); a live run holds the lock anyway."""
    for stale in target.parent.glob(f".{target.name}.partial-*"):
        pid = stale.name.rsplit("-", 1)[-1]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(stale, ignore_errors=True)
            log.info("removed the partial twin of an interrupted run: %s", stale)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON through a temporary file, fsync and rename, so a reader never sees half a file."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2, sort_keys=True, default=str)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def swap_into_place(staging: Path, target: Path) -> None:
    """Move the finished twin into place; an old twin is moved aside first and removed only after the move."""
    old = None
    if target.exists():
        old = target.parent / f".{target.name}.old-{os.getpid()}"
        os.replace(target, old)
    try:
        os.replace(staging, target)
    except BaseException:
        if old is not None:
            os.replace(old, target)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
