"""``keep_unchanged`` (also ``keep_reference``): the known data stays, the changed new elements come in."""

from __future__ import annotations

from typing import Any

from gdt_pipeline import StageContext

from ._compose import fuse, fusion_stage
from ._segments import SegmentParams

KEEP = "Known data stays; changed new elements come in; unchanged new ones are hidden."


class KeepUnchangedParams(SegmentParams):
    """``keep_unchanged``: only the segmentation parameters."""


def keep_unchanged(ctx: StageContext) -> dict[str, Any]:
    """Known data stays; changed new elements come in; unchanged new ones are hidden."""
    return fuse(ctx, None)


KEEP_UNCHANGED = fusion_stage("keep_unchanged", KeepUnchangedParams, keep_unchanged, KEEP, needs_rov=False)
KEEP_REFERENCE = fusion_stage("keep_reference", KeepUnchangedParams, keep_unchanged,
                              KEEP + " (the same as keep_unchanged)", needs_rov=False)
