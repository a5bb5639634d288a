"""Region-of-view stages (paper Sec. 4.1): each is a builder of the volume its sensors measured, made a stage by
``gdt_pipeline.region_of_view.rov_stage``, which judges what each station saw inside it (depth images by default,
the paper's Plane of Sight under ``sight: plane``; see that module):

- ``sensor_frustum``: the union of the sensors' frusta, per recent dataset with viewpoints: a pinhole frustum from
  the dataset's station when it has a target and a pinhole scanner (a pose file beside the input,
  ``<scan>_pose.json``, as the simulator writes: viewpoint, target, field of view, aspect, range), else the tightest
  pinhole frustum around the directions to the dataset's own points (plus a margin); near and far from the
  parameters or the data. Each frustum is its own station's volume.
- ``manual_box``: a user-given axis-aligned box, as the paper did for its experiments; the stations are the
  recent data's viewpoints.
- ``coverage``: for data without stations (airborne, voxelised clouds): judged from the recent data's own coverage,
  or along a stated sight direction (nadir), without a sight test from stations.
"""

from __future__ import annotations

from gdt_pipeline import StageSpec, hookimpl

from . import coverage, manual_box, sensor_frustum
from .manual_box import BoxParams
from .sensor_frustum import FrustumParams

__all__ = ["BoxParams", "FrustumParams", "gdt_stages"]


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in region-of-view stages."""
    return [sensor_frustum.SPEC, manual_box.SPEC, coverage.SPEC]
