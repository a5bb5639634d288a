"""Geometry helpers shared by stages (and by the simulator and evaluation): ray-casting scenes, point-to-mesh
distance, surface sampling, normals, orthonormal frames, closed-form 3x3 algebra and the nearest-element index of a
composite."""

from ..types.triangles import triangle_areas, triangle_normals, triangle_points
from .frames import beam_frames
from .linalg import det3, inv3, quad_inv3, sym3
from .normals import estimate_normals, knn_reach
from .raycasting import distance_to, line_crossings, list_intersections, raycasting_scene
from .reference import NearestResult, ReferenceIndex
from .sampling import sample_surface

__all__ = ["NearestResult", "ReferenceIndex", "beam_frames", "det3", "distance_to", "estimate_normals", "inv3",
           "knn_reach", "line_crossings", "list_intersections", "quad_inv3", "raycasting_scene", "sample_surface",
           "sym3", "triangle_areas", "triangle_normals", "triangle_points"]
