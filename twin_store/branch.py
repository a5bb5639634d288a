"""A new twin folder that starts as the first epochs of another: where an append (or a rebuild from an epoch) is
written before it is swapped in. The kept layers are hard links to the twin's own files, so they stay byte for byte
what they were, and an append costs nothing per epoch of history."""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from pathlib import Path

from pxr import Sdf

from .errors import TwinStoreError
from .layers import export_atomic, open_layer
from .names import EPOCH_DIR, ROOT_NAME


def kept_files(digests: dict[str, str], epochs: Sequence[str]) -> dict[str, str]:
    """The layer files (the epoch layers and their payload layers) of ``epochs``, relative path -> sha256."""
    prefixes = tuple(f"{EPOCH_DIR}/{eid}." for eid in epochs)
    return {rel: digest for rel, digest in digests.items() if rel.startswith(prefixes)}


def branch(source: Path, target: Path, epochs: Sequence[str], digests: dict[str, str]) -> int:
    """Make ``target`` a twin holding the epochs ``epochs`` (oldest first, a prefix of ``source``'s) of the twin at
    ``source``, whose layer sha256s are ``digests``; return how many files had to be copied (not linked)."""
    if target.exists():
        raise TwinStoreError(f"{target} already exists; a twin is branched into a new folder only")
    (target / EPOCH_DIR).mkdir(parents=True)
    files = kept_files(digests, epochs)
    copied = 0
    for rel in sorted(files):
        src, dst = source / rel, target / rel
        if not src.is_file():
            raise TwinStoreError(f"layer {src} is missing (recorded sha256 {files[rel]}); the twin is damaged")
        try:
            os.link(src, dst)
        except OSError:  # a filesystem without hard links: the bytes are the same, only the cost grows
            shutil.copy2(src, dst)
            copied += 1
    root = Sdf.Layer.CreateAnonymous("root.usda")
    root.TransferContent(open_layer(source / ROOT_NAME))
    root.subLayerPaths.clear()
    for eid in reversed(list(epochs)):
        root.subLayerPaths.append(f"{EPOCH_DIR}/{eid}.usdc")
    data = dict(root.customLayerData)
    data["gdt"] = {**dict(data.get("gdt", {})), "layer_sha256": files}
    root.customLayerData = data
    export_atomic(root, target / ROOT_NAME)
    return copied
