"""The twin store: a USD root stage with one layer per epoch, per-element primvars and provenance, atomic writes.

Depends on numpy and pxr only. Modules: ``names`` (codes, paths, primvar docs), ``elements`` (ElementSet and its
USD prim), ``guides`` (regions of view, segments), ``history`` (epoch records, diffs), ``layers`` (atomic layer
files), ``lock`` (the writer lock), ``store`` (TwinStore)."""

from .elements import ElementSet
from .errors import TwinStoreError
from .history import EpochRecord, SetDiff
from .lock import lock_path, writer_lock
from .names import REASON_NAMES, STATE_COLORS, STATE_NAMES
from .store import TwinStore

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
