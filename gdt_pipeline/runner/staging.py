"""Building a twin beside its target and moving it into place only when complete (the swap itself, and recovery
from a killed swap, are the twin store's: ``twin_store.swap``)."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

from twin_store import foreign_files, partial_path, recover_leftovers, swap_into_place

from ..errors import GdtError

log = logging.getLogger("gdt.run")

__all__ = ["check_overwritable", "recover", "staging_path", "swap_into_place", "write_json_atomic"]


def staging_path(target: Path) -> Path:
    """Where this process builds the twin before it moves it to ``target``."""
    return partial_path(target)


def recover(target: Path) -> None:
    """Put back or clean up what killed runs left beside ``target`` (call it holding the writer lock); log it."""
    for action, message in recover_leftovers(target):
        if action == "removed":
            log.info(message)
        else:
            log.warning(message)


def check_overwritable(target: Path, how: str = "--overwrite replaces") -> None:
    """Refuse to replace a twin folder that holds files the twin does not own (the user's own files); ``how`` says
    what would replace it."""
    foreign = foreign_files(target)
    if foreign:
        shown = ", ".join(foreign[:10]) + (f" and {len(foreign) - 10} more" if len(foreign) > 10 else "")
        verb = "overwrite" if how.startswith("--overwrite") else "write to"
        raise GdtError(f"refusing to {verb} twin {target}: it holds files the twin does not own ({shown}); "
                       f"{how} the whole folder, so move them out of it first")


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON through a temporary file, fsync and rename, so a reader never sees half a file."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2, sort_keys=True, default=str)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
