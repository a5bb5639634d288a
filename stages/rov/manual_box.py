"""``manual_box``: the region of view is a user-given axis-aligned box, as the paper did for its experiments."""

from __future__ import annotations

from pydantic import Field

from gdt_pipeline import RegionOfView, StageContext
from gdt_pipeline.region_of_view import SightParams, Volume, rov_stage


class BoxParams(SightParams):
    """A user-given box."""

    lower: list[float] = Field(min_length=3, max_length=3, description="Lower corner (twin units).")
    upper: list[float] = Field(min_length=3, max_length=3, description="Upper corner (twin units).")


def box_volume(ctx: StageContext) -> Volume:
    """The box of the parameters; the stations are the recent data's viewpoints."""
    p = ctx.params
    return Volume(RegionOfView.box(p.lower, p.upper), [f"box {p.lower} .. {p.upper}"])


SPEC = rov_stage(name="manual_box", build=box_volume, params=BoxParams, version="1.1.0",
                 description="A user-given box; in view where a station saw the element's place (`sight`: "
                             "depth images by default).")
