"""The twin store: a USD root stage with one layer per epoch, per-element primvars and provenance, atomic writes.

Depends on numpy and pxr only."""

from .store import STATE_COLORS, STATE_NAMES, ElementSet, TwinStore, TwinStoreError

__all__ = ["STATE_COLORS", "STATE_NAMES", "ElementSet", "TwinStore", "TwinStoreError"]
