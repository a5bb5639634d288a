"""What a twin owns and whether it is intact: layer sha256s checked against the record, the run record checked.

Every epoch layer's sha256 is recorded when it is written, in the root layer's ``customLayerData["gdt"]
["layer_sha256"]`` (keyed by the sublayer path, ``epochs/E1.usdc``) and, by ``gdt run``, in ``gdt.lock``. A layer
is verified before it is used: a flipped byte, a truncated or a missing file is a TwinStoreError naming the file,
the recorded and the actual sha256, never data.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

from .errors import TwinStoreError
from .names import EPOCH_DIR, ROOT_NAME, RUN_LOCK_NAME

# the temp files the store and the runner write before renaming (a killed write may leave one behind)
_TEMP = re.compile(r"\..+\.tmp-\d+\.usd[ac]?|" + re.escape(RUN_LOCK_NAME) + r"\.tmp")


def sha256_file(path: Path) -> str:
    """The sha256 of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _stat_key(path: Path) -> tuple[int, int, int]:
    st = os.stat(path)
    return st.st_ino, st.st_size, st.st_mtime_ns


class LayerDigests:
    """Verified sha256s of layer files, remembered while the file is unchanged (same inode, size, mtime)."""

    def __init__(self) -> None:
        self._known: dict[str, tuple[tuple[int, int, int], str]] = {}

    def remember(self, path: Path, digest: str) -> None:
        """Note the digest of a file just written."""
        self._known[str(path)] = (_stat_key(path), digest)

    def actual(self, path: Path) -> str:
        """The file's sha256 (re-read only when the file changed since it was last read)."""
        key = _stat_key(path)
        hit = self._known.get(str(path))
        if hit is not None and hit[0] == key:
            return hit[1]
        digest = sha256_file(path)
        self._known[str(path)] = (key, digest)
        return digest

    def verify(self, path: Path, recorded: str | None, epoch_id: str) -> None:
        """Raise a TwinStoreError naming the layer unless it exists and has its recorded sha256 (if one is)."""
        if not path.is_file():
            known = f" (recorded sha256 {recorded})" if recorded else ""
            raise TwinStoreError(f"layer {path} of epoch {epoch_id} is missing{known}; the twin is damaged: "
                                 f"restore the file from a backup or re-run the workflow with --overwrite")
        if recorded is None:
            return  # a twin written before layers were hashed
        actual = self.actual(path)
        if actual != recorded:
            raise TwinStoreError(f"layer {path} of epoch {epoch_id} is corrupted: its sha256 is {actual}, the "
                                 f"twin recorded {recorded} when it was written; restore the file from a backup "
                                 f"or re-run the workflow with --overwrite")


def run_lock_problems(twin: Path, recorded: dict[str, str]) -> list[str]:
    """What is wrong with a twin's gdt.lock (missing, unparsable, layer sha256s that disagree with the root)."""
    path = twin / RUN_LOCK_NAME
    if not path.is_file():
        return [f"{path} is missing: the run record (seed, packages, cache keys) is gone; the layers still verify "
                f"against {ROOT_NAME}, re-run the workflow with --overwrite to write it again"]
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        return [f"{path} is not a valid run record: byte {exc.start} is not UTF-8"]
    except json.JSONDecodeError as exc:
        return [f"{path} is not a valid run record: {exc.msg} at line {exc.lineno}:{exc.colno}"]
    if not isinstance(data, dict) or not isinstance(data.get("epochs"), list):
        return [f"{path} is not a valid run record: it holds no 'epochs' list"]
    in_lock = data.get("layer_sha256") or {}
    if not isinstance(in_lock, dict):
        return [f"{path} is not a valid run record: 'layer_sha256' is not a mapping"]
    return [f"{path} records sha256 {digest} for {layer}, but {ROOT_NAME} records {recorded[layer]}"
            for layer, digest in sorted(in_lock.items()) if layer in recorded and recorded[layer] != digest]


def foreign_files(twin: Path) -> list[str]:
    """Files and folders inside a twin folder that the twin does not own (relative paths, sorted)."""
    out = []
    for entry in sorted(Path(twin).iterdir()):
        name = entry.name
        if name == EPOCH_DIR and entry.is_dir() and not entry.is_symlink():
            out += [f"{EPOCH_DIR}/{e.name}" for e in sorted(entry.iterdir())
                    if not (e.is_file() and (e.suffix == ".usdc" or _TEMP.fullmatch(e.name)))]
        elif not (entry.is_file() and (name in (ROOT_NAME, RUN_LOCK_NAME) or _TEMP.fullmatch(name))):
            out.append(name + ("/" if entry.is_dir() else ""))
    return out
