"""The twin store: a USD root stage with one layer per epoch, per-element primvars and provenance, atomic writes.

Depends on numpy and pxr only."""

from .store import (
    REASON_NAMES,
    STATE_COLORS,
    STATE_NAMES,
    ElementSet,
    EpochRecord,
    SetDiff,
    TwinStore,
    TwinStoreError,
    lock_path,
    writer_lock,
)

__all__ = [
    "REASON_NAMES",
    "STATE_COLORS",
    "STATE_NAMES",
    "ElementSet",
    "EpochRecord",
    "SetDiff",
    "TwinStore",
    "TwinStoreError",
    "lock_path",
    "writer_lock",
]
