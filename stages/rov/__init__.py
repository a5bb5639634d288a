"""Region of View (paper Sec. 4.1): what the sensors of an epoch saw, so that reference geometry the recent data
does not show is called "removed" only where a sensor could have seen it.

- ``sensor_frustum``: the bounding volume is the union of the sensors' frusta: per recent dataset with viewpoints,
  a pinhole frustum from the dataset's station when it has a target and a pinhole scanner (a pose file beside the
  input, ``<scan>_pose.json``, as the simulator writes: viewpoint, target, field of view, aspect, range; the engine
  reads it for every stage), else the tightest pinhole frustum around the directions to the
  dataset's own points (plus a margin); near and far from the parameters or the data.
- ``manual_box``: a user-given axis-aligned box, as the paper did for its experiments.

Both then remove occlusion with the Plane of Sight (POS): a polygon through the sensor positions (a point for one
sensor, a segment for two); for each reference element inside the volume a ray runs from it to the closest point of
the POS; where it crosses the recent data an odd number of times (Open3D ``list_intersections`` on the segment), the
element is not in view (the paper's rule). Point-cloud recent data first gets an intermediate surface (Open3D ball
pivoting: it keeps only the measured side, which the parity rule needs), stated in the report. An element in view is
"matched" when recent data lies within ``match_distance`` of it; the fusion marks in-view, unmatched elements
removed and the others outside the region of view.
"""

from __future__ import annotations

from gdt_pipeline import StageSpec, hookimpl

from ._occlusion import OcclusionParams
from .manual_box import BoxParams, manual_box
from .sensor_frustum import FrustumParams, sensor_frustum

__all__ = ["BoxParams", "FrustumParams", "OcclusionParams", "gdt_stages"]


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in region-of-view stages."""
    common = {"family": "rov", "version": "1.1.0", "requires": ("recent",), "optional": ("reference",),
              "provides": ("rov",)}
    return [
        StageSpec(name="sensor_frustum", params=FrustumParams, run=sensor_frustum,
                  description="Union of the sensors' frusta, minus what recent data occludes (Plane of Sight).",
                  **common),
        StageSpec(name="manual_box", params=BoxParams, run=manual_box,
                  description="A user-given box, minus what recent data occludes (Plane of Sight).", **common),
    ]
