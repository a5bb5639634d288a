"""Geometry helpers shared by stages (and by the simulator and evaluation): ray-casting scenes, point-to-mesh
distance, surface sampling, orthonormal frames and the nearest-element index of a composite."""

from .frames import beam_frames
from .raycasting import distance_to, raycasting_scene
from .reference import NearestResult, ReferenceIndex
from .sampling import sample_surface

__all__ = ["NearestResult", "ReferenceIndex", "beam_frames", "distance_to", "raycasting_scene", "sample_surface"]
