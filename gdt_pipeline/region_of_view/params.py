"""The parameters every region-of-view stage shares: how sight is judged inside the stage's volume."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, PositiveFloat


class SightParams(BaseModel):
    """How a region-of-view stage judges what its sensors saw inside its volume: the sight test (``sight``: depth
    images per station, the default; the paper's Plane of Sight; rays to each station), occlusion and matching.
    Every region-of-view stage's parameters extend these."""

    model_config = ConfigDict(extra="forbid")
    occlusion: bool = Field(True, description="Remove elements hidden behind recent data (Plane of Sight).")
    rule: Literal["odd", "any"] = Field("odd", description="Occluded when the sight ray crosses the recent data an "
                                                           "odd number of times (the paper), or at all.")
    offset: PositiveFloat | None = Field(None, description="The sight ray starts this far towards the POS, so the "
                                                           "element's own measured surface is not counted (default: "
                                                           "3 × the recent data's point spacing).")
    match_distance: PositiveFloat | None = Field(None, description="Recent data within this distance of an element "
                                                                   "matches it (default: 3 × the point spacing; "
                                                                   "at least 3σ of the recent element).")
    cull_back_faces: bool = Field(True, description="Reference facets facing away from every sensor are not in "
                                                    "view (needs outward facet normals, as CAD solids have).")
    viewpoints: list[list[float]] | None = Field(None, description="Sensor positions for the POS (default: those "
                                                                   "the inputs carry).")
    confirmed_occlude: bool = Field(True, description="Reference facets the recent data matches (confirmed present) "
                                                      "hide what lies behind them too, seen from their front.")
    sight: Literal["depth", "plane", "stations"] = Field(
        "depth", description="depth: each station's depth image of its own measured points; an element's place is "
                             "seen when measured surface lies at its depth (present) or clearly behind it (seen "
                             "through: removed), hidden when it stands clearly in front; no surface reconstruction. "
                             "plane: the sight ray runs to the Plane of Sight through all sensor positions and "
                             "crosses a ball-pivoted surface of the recent points (the paper); stations: to each "
                             "sensor whose own frustum holds the element, in view when any such ray is clear.")
    k_sigma: PositiveFloat = Field(3.0, description="sight: depth: measured surface within k σ (the point's and the "
                                                    "element's, along the ray) of an element's depth is at it.")
    pixel_scale: PositiveFloat = Field(1.0, description="sight: depth: the depth image's pixel as a multiple of the "
                                                        "angle between neighbouring rays.")
    samples_per_facet: int = Field(64, ge=1, le=4096, description="sight: depth: the most samples a reference facet "
                                                                  "is judged on (about one per point spacing²).")
