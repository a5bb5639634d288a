"""``keep_unchanged`` (also ``keep_reference``): the known data stays, the changed new elements come in."""

from __future__ import annotations

from typing import Any

from gdt_pipeline import StageContext

from ._compose import fuse
from ._segments import SegmentParams


class KeepUnchangedParams(SegmentParams):
    """``keep_unchanged``: only the segmentation parameters."""


def keep_unchanged(ctx: StageContext) -> dict[str, Any]:
    """Known data stays; changed new elements come in; unchanged new ones are hidden."""
    return fuse(ctx, None)
