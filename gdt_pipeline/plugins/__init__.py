"""Plugin system: what a plugin declares (``specs``) and how the engine finds plugins (``registry``)."""

from .registry import Registry, blocked_from_env, load_registry, unknown_name_message
from .specs import (
    BLOCK_ENV,
    ENTRY_POINT_GROUP,
    FAMILIES,
    PROJECT,
    Family,
    GdtSpecs,
    NullProgress,
    Progress,
    ProgressTask,
    ReaderSpec,
    ReadRequest,
    StageContext,
    StageSpec,
    hookimpl,
    hookspec,
)

__all__ = ["BLOCK_ENV", "ENTRY_POINT_GROUP", "FAMILIES", "PROJECT", "Family", "GdtSpecs", "NullProgress", "Progress",
           "ProgressTask", "ReadRequest", "ReaderSpec", "Registry", "StageContext", "StageSpec", "blocked_from_env",
           "hookimpl", "hookspec", "load_registry", "unknown_name_message"]
