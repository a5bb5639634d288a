"""The region of view (paper Sec. 4.1), the public API of region-of-view stages: what the sensors of an epoch saw,
so that a reference element the recent data does not show is called removed only where a sensor could have seen it.

A stage is a builder and the shared machinery: the builder (``rov_stage(build=...)``) returns a ``Volume``, the
closed surfaces its sensors measured inside and the stations inside them; ``look`` then judges every reference
element inside the volume and reports, per item, which elements are in view and which of those the recent data
matched (``ItemView``), and the fusion marks in-view, unmatched elements removed and the rest outside the region of
view. How sight is judged is the same for every builder (``SightParams.sight``):

- ``depth`` (the default): per station a depth image of its own measured points; every reference element is
  sampled over its area, and a sample is present where measured surface lies at its depth (within k σ of the
  point's and the element's uncertainty along the facet's normal), seen through (removed) where the station
  measured clearly behind it, hidden where surface stands clearly in front. No surface is reconstructed. Removal
  needs that positive evidence of seeing through the element's place (``depth``, ``depth_view``).
- ``plane``: the paper's Plane of Sight, a polygon through the sensor positions; a ray from each element to its
  closest point crosses a ball-pivoted surface of the recent points an odd number of times where the element is
  occluded (``occlusion``).
- ``stations``: a ray to each station whose own volume holds the element; in view when any is clear.

``Station`` is one sensor position with the recent datasets it measured and its own volume (``contains``), and
``view_frame`` the frame of a sensor looking along a direction (for builders of pinhole frusta).
"""

from .depth import Station, view_frame
from .look import look, point_spacing
from .params import SightParams
from .stage import Build, Volume, rov_stage

__all__ = ["Build", "SightParams", "Station", "Volume", "look", "point_spacing", "rov_stage", "view_frame"]
