"""Open3D ray-casting scenes and point-to-mesh distances: the point↔mesh work of stages, simulator and evaluation."""

from __future__ import annotations

import numpy as np


def raycasting_scene(meshes: list):  # -> o3d.t.geometry.RaycastingScene
    """An Open3D raycasting scene holding the triangles of ``meshes``: objects with vertices and faces, or
    (vertices, faces) pairs; meshes without faces are skipped."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        verts, faces = (m.vertices, m.faces) if hasattr(m, "faces") else m
        if len(faces):
            scene.add_triangles(o3d.core.Tensor(np.asarray(verts, dtype=np.float32)),
                                o3d.core.Tensor(np.asarray(faces, dtype=np.uint32)))
    return scene


def distance_to(meshes: list, points: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest of ``meshes`` (inf when there are none)."""
    import open3d as o3d

    if not meshes or not len(points):
        return np.full(len(points), np.inf)
    return raycasting_scene(meshes).compute_distance(
        o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy().astype(np.float64)


def list_intersections(scene: object, rays: np.ndarray) -> dict[str, np.ndarray]:
    """Every crossing of each ray (rows: origin, direction; float32) with ``scene``: ``ray_splits`` (R+1),
    ``ray_ids``, ``geometry_ids``, ``primitive_ids`` and ``t_hit``, as numpy arrays. Open3D's own call is not
    made for zero rays: its prefix sum then runs from the array's end backwards through memory (a segfault in
    Open3D 0.20; it killed a 50 M-point tiled run at its first tile whose crop cast no line)."""
    import open3d as o3d

    if not len(rays):
        empty = np.zeros(0, dtype=np.uint32)
        return {"ray_splits": np.zeros(1, dtype=np.uint32), "ray_ids": empty, "geometry_ids": empty,
                "primitive_ids": empty, "t_hit": np.zeros(0, dtype=np.float32)}
    ans = scene.list_intersections(o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32)))  # type: ignore[attr-defined]
    return {k: ans[k].numpy() for k in ("ray_splits", "ray_ids", "geometry_ids", "primitive_ids", "t_hit")}


def line_crossings(scene: object, normals: list[np.ndarray], points: np.ndarray, axis: np.ndarray,
                   reach: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every crossing of each line (through ``points`` along unit ``axis``, in ``scene``'s coordinates) with the
    meshes of the Open3D raycasting ``scene`` within ``reach`` of its point: which line, how far the point lies
    beyond the crossing along the line, and the facet's normal (``normals``: per geometry of the scene, per
    facet)."""
    start = (points - axis * reach[:, None]).astype(np.float32)
    ans = list_intersections(scene, np.hstack([start, axis.astype(np.float32)]))
    ray = ans["ray_ids"].astype(np.int64)
    geometry, primitive = ans["geometry_ids"].astype(np.int64), ans["primitive_ids"].astype(np.int64)
    normal = np.zeros((len(ray), 3))
    for g, table in enumerate(normals):
        at = geometry == g
        normal[at] = table[primitive[at]]
    along = reach[ray] - ans["t_hit"].astype(np.float64)
    near = np.abs(along) <= reach[ray]
    return ray[near], along[near], normal[near]
