"""Which facets of a mesh a set of scanner stations could see: the per-facet in-view truth of a generated scene."""

from __future__ import annotations

import numpy as np

from ..geometry import raycasting_scene
from .scanner import ScannerSpec


def facets_in_view(mesh, stations: np.ndarray, blockers: list, spec: ScannerSpec, target: np.ndarray) -> np.ndarray:
    """Whether any station sees each facet's centroid: inside its field of view, in range, not occluded."""
    import open3d as o3d

    scene = raycasting_scene(blockers)
    c = mesh.triangles_center
    seen = np.zeros(len(c), dtype=bool)
    for eye in stations:
        d = c - eye
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        fwd = (target - eye) / np.linalg.norm(target - eye)
        half_h = np.radians(spec.fov_deg) / 2
        half_v = np.arctan(np.tan(half_h) / spec.aspect)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        inside = (np.abs(np.arctan2(d @ right, d @ fwd)) <= half_h) & (np.abs(np.arctan2(d @ up, d @ fwd)) <= half_v)
        facing = np.einsum("ij,ij->i", mesh.face_normals, -d) > 0.05
        t = scene.cast_rays(o3d.core.Tensor(np.hstack([np.broadcast_to(eye, d.shape), d]).astype(np.float32)))
        clear = ~(t["t_hit"].numpy() < dist - 1e-4) if blockers else np.ones(len(c), bool)
        seen |= inside & facing & clear & (dist <= spec.max_range)
    return seen


def facets_in_view_of_stations(mesh, stations: list[tuple[np.ndarray, np.ndarray]], blockers: list,
                               spec: ScannerSpec) -> np.ndarray:
    """Whether any of the stations (each an (eye, target) pair with its own target) sees each facet."""
    seen = np.zeros(len(mesh.faces), dtype=bool)
    for eye, target in stations:
        seen |= facets_in_view(mesh, eye[None, :], blockers, spec, target)
    return seen
