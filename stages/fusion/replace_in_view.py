"""``replace_in_view``: the newest data replaces what it images inside the region of view."""

from __future__ import annotations

from typing import Any

from gdt_pipeline import StageContext

from ._compose import fuse, fusion_stage
from ._segments import SegmentParams


class ReplaceInViewParams(SegmentParams):
    """``replace_in_view``: only the segmentation parameters."""


def replace_in_view(ctx: StageContext) -> dict[str, Any]:
    """The newest data replaces the known data it images inside the region of view."""
    return fuse(ctx, "replace_in_view")


SPEC = fusion_stage("replace_in_view", ReplaceInViewParams, replace_in_view,
                    "The newest data replaces what it images inside the region of view.", needs_rov=True)
