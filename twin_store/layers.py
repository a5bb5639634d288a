"""USD layer files on disk: written atomically (temp file, fsync, rename) and re-read fresh; a file USD cannot read
is a TwinStoreError naming it."""

from __future__ import annotations

import os
from pathlib import Path

from pxr import Sdf, Tf

from .errors import TwinStoreError
from .faults import fault
from .integrity import sha256_file


def fsync_path(path: Path) -> None:
    """Flush a file, or a folder's entries after a rename, to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def export_atomic(layer: Sdf.Layer, target: Path, steps: tuple[str, str] | None = None) -> str:
    """Export a layer to a temp file with the same extension (USD picks the format by it), fsync, rename; return
    the file's sha256. ``steps`` names the fault-injection points after the export and after the rename."""
    tmp = target.with_name(f".{target.stem}.tmp-{os.getpid()}{target.suffix}")
    try:
        ok = layer.Export(str(tmp))
    except Tf.ErrorException as exc:
        raise TwinStoreError(f"could not write {target}: {usd_message(exc)}") from None
    if not ok:
        raise TwinStoreError(f"could not write {tmp}")
    fsync_path(tmp)
    digest = sha256_file(tmp)
    if steps:
        fault(steps[0])
    os.replace(tmp, target)
    fsync_path(target.parent)
    if steps:
        fault(steps[1])
    cached = Sdf.Layer.Find(str(target))
    if cached is not None:
        cached.Reload(force=True)
    return digest


def open_layer(path: Path) -> Sdf.Layer:
    """The layer at ``path`` as it is on disk now (a cached copy is reloaded, since another writer may have
    replaced the file); a file USD cannot read is a TwinStoreError naming it."""
    try:
        layer = Sdf.Layer.Find(str(path))
        if layer is not None:
            if not layer.Reload(force=True):
                raise TwinStoreError(f"cannot read USD layer {path}")
            return layer
        layer = Sdf.Layer.FindOrOpen(str(path))
    except Tf.ErrorException as exc:
        raise TwinStoreError(f"cannot read USD layer {path}: {usd_message(exc)}") from None
    if layer is None:
        raise TwinStoreError(f"cannot open USD layer {path}")
    return layer


def usd_message(exc: Tf.ErrorException) -> str:
    """The gist of a USD error: its commentary, without the C++ function and source location."""
    parts = []
    for err in exc.args:
        try:
            parts.append(" ".join(str(getattr(err, "commentary", err)).split()))
        except UnicodeDecodeError:  # USD quotes the bad bytes, which Python cannot decode
            parts.append("the file holds bytes that are not UTF-8 text where USD expects text")
    return "; ".join(parts)[:300] or "USD could not read it"
