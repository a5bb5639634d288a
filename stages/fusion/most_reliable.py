"""``most_reliable``: as keep_unchanged, but more precise new data replaces measured data in view."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from gdt_pipeline import StageContext

from ._compose import fuse, fusion_stage
from ._segments import SegmentParams


class MostReliableParams(SegmentParams):
    """When new data replaces the known data."""

    replace_design: bool = Field(False, description="Let precise measurements replace as-designed (CAD) elements "
                                                    "too (default: the design stays where it is confirmed).")
    ratio: float = Field(1.0, gt=0, le=1, description="New data must have √det Σ below this share of the known "
                                                      "data's.")


def most_reliable(ctx: StageContext) -> dict[str, Any]:
    """Unchanged new data with a smaller √det Σ replaces the measured known data it images in view."""
    return fuse(ctx, "most_reliable")


SPEC = fusion_stage("most_reliable", MostReliableParams, most_reliable,
                    "As keep_unchanged, but more precise new data replaces measured data in view.", needs_rov=True)
