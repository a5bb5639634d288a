"""The twin store: a USD root stage with one layer per epoch, per-element primvars and provenance, atomic writes.

Depends on numpy and pxr only. Modules: ``names`` (codes, paths, primvar docs), ``elements`` (ElementSet and its
USD prim), ``segments`` (the Segment record), ``guides`` (regions of view, segments as prims), ``history`` (one
entry per epoch, diffs), ``layers`` (atomic layer files), ``integrity`` (layer sha256s, what a twin folder owns),
``swap`` (replacing a whole twin, recovery after a kill), ``faults`` (the kill tests' injection points), ``lock``
(the writer lock), ``lean`` (set by set, value by value reads), ``set_source`` (sets made as the writer reads
them), ``store`` (TwinStore)."""

from .elements import ElementSet, display_colours
from .errors import TwinStoreError
from .faults import FAULT_STEPS, fault
from .history import EpochEntry, SetDiff
from .integrity import foreign_files, sha256_file
from .lean import LeanSet
from .lock import lock_path, writer_lock
from .names import REASON_NAMES, RUN_LOCK_NAME, STATE_COLORS, STATE_NAMES, state_colours
from .payloads import preview_rows
from .segments import Segment
from .set_source import RowsOnDemand, SetsOnDemand, set_keys, whole
from .store import TwinStore
from .swap import partial_path, recover_leftovers, swap_into_place

__all__ = [
    "FAULT_STEPS",
    "REASON_NAMES",
    "RUN_LOCK_NAME",
    "STATE_COLORS",
    "STATE_NAMES",
    "ElementSet",
    "EpochEntry",
    "LeanSet",
    "RowsOnDemand",
    "Segment",
    "SetDiff",
    "SetsOnDemand",
    "TwinStore",
    "TwinStoreError",
    "display_colours",
    "fault",
    "foreign_files",
    "lock_path",
    "partial_path",
    "preview_rows",
    "recover_leftovers",
    "set_keys",
    "sha256_file",
    "state_colours",
    "swap_into_place",
    "whole",
    "writer_lock",
]
