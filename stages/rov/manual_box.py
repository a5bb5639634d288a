"""``manual_box``: the region of view is a user-given axis-aligned box, as the paper did for its experiments."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from gdt_pipeline import RegionOfView, StageContext

from ._look import look
from ._occlusion import OcclusionParams


class BoxParams(OcclusionParams):
    """A user-given box."""

    lower: list[float] = Field(min_length=3, max_length=3, description="Lower corner (twin units).")
    upper: list[float] = Field(min_length=3, max_length=3, description="Upper corner (twin units).")


def manual_box(ctx: StageContext) -> dict[str, Any]:
    """A user-given box, minus what recent data occludes."""
    p = ctx.params
    rov = RegionOfView.box(p.lower, p.upper)
    return look(ctx, rov, [f"box {p.lower} .. {p.upper}"])
