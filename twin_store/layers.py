"""USD layer files on disk: written atomically (temp file, fsync, rename) and re-read fresh."""

from __future__ import annotations

import os
from pathlib import Path

from pxr import Sdf

from .errors import TwinStoreError


def fsync_path(path: Path) -> None:
    """Flush a file, or a folder's entries after a rename, to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def export_atomic(layer: Sdf.Layer, target: Path) -> None:
    """Export a layer to a temp file with the same extension (USD picks the format by it), fsync, rename."""
    tmp = target.with_name(f".{target.stem}.tmp-{os.getpid()}{target.suffix}")
    if not layer.Export(str(tmp)):
        raise TwinStoreError(f"could not write {tmp}")
    fsync_path(tmp)
    os.replace(tmp, target)
    fsync_path(target.parent)
    cached = Sdf.Layer.Find(str(target))
    if cached is not None:
        cached.Reload(force=True)


def open_layer(path: Path) -> Sdf.Layer:
    """The layer at ``path`` as it is on disk now (a cached copy is reloaded, since another writer may have
    replaced the file)."""
    layer = Sdf.Layer.Find(str(path))
    if layer is not None:
        layer.Reload(force=True)
        return layer
    layer = Sdf.Layer.FindOrOpen(str(path))
    if layer is None:
        raise TwinStoreError(f"cannot open USD layer {path}")
    return layer
