"""Occlusion by the Plane of Sight (paper Sec. 4.1) and by the stations: sight segments from reference elements to
the sensors, and whether recent data, or a reference facet it confirmed, crosses them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from ..geometry import list_intersections, raycasting_scene
from ..types import Dataset
from .params import SightParams


def pos_closest(points: np.ndarray, viewpoints: np.ndarray) -> np.ndarray:
    """The closest point of the Plane of Sight (the polygon through the viewpoints) to each point."""
    vp = np.atleast_2d(viewpoints)
    if len(vp) == 1:
        return np.broadcast_to(vp[0], points.shape).copy()
    centre = vp.mean(axis=0)
    _, s, vt = np.linalg.svd(vp - centre)
    if len(vp) == 2 or s[1] < 1e-9 * max(s[0], 1e-12):  # collinear: the POS is a segment
        a, b = vp[np.argmin((vp - centre) @ vt[0])], vp[np.argmax((vp - centre) @ vt[0])]
        t = np.clip(((points - a) @ (b - a)) / max(float((b - a) @ (b - a)), 1e-30), 0, 1)
        return a + t[:, None] * (b - a)
    e1, e2 = vt[0], vt[1]
    uv = np.column_stack([(vp - centre) @ e1, (vp - centre) @ e2])
    hull = uv[ConvexHull(uv).vertices]
    q = np.column_stack([(points - centre) @ e1, (points - centre) @ e2])
    # inside the polygon: the projection; outside: the closest point on its boundary edges
    best = q.copy()
    inside = np.ones(len(q), dtype=bool)
    best_d = np.full(len(q), np.inf)
    edge_pt = np.zeros_like(q)
    for i in range(len(hull)):  # a loop over the few polygon edges; the points are vectorised
        a, b = hull[i], hull[(i + 1) % len(hull)]
        ab = b - a
        inside &= (ab[0] * (q[:, 1] - a[1]) - ab[1] * (q[:, 0] - a[0])) >= 0
        t = np.clip(((q - a) @ ab) / float(ab @ ab), 0, 1)
        c = a + t[:, None] * ab
        d = np.linalg.norm(q - c, axis=1)
        closer = d < best_d
        best_d[closer], edge_pt[closer] = d[closer], c[closer]
    best[~inside] = edge_pt[~inside]
    return centre + best[:, :1] * e1 + best[:, 1:] * e2


def occluded(origins: np.ndarray, targets: np.ndarray, scene, rule: str) -> np.ndarray:
    """Whether each sight segment crosses the recent surfaces (an odd number of times, or at all)."""
    if not len(origins) or scene is None:
        return np.zeros(len(origins), dtype=bool)
    ray, _ = segment_hits(scene, origins, targets)
    counts = np.bincount(ray, minlength=len(origins))
    return counts % 2 == 1 if rule == "odd" else counts > 0


def segment_hits(scene, origins: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every crossing of the scene strictly between each origin and its target: (segment index, triangle id)."""
    rays = np.hstack([origins, targets - origins]).astype(np.float32)  # direction unnormalised: t in [0, 1] = segment
    ans = list_intersections(scene, rays)
    t = ans["t_hit"]
    ray = np.repeat(np.arange(len(origins)), np.diff(ans["ray_splits"].astype(np.int64)))
    on_segment = (t > 0) & (t < 1)
    return ray[on_segment], ans["primitive_ids"][on_segment]


def shadowed(origins: np.ndarray, targets: np.ndarray, tree: cKDTree, radius: float, chunk: int = 2_000_000
              ) -> np.ndarray:
    """Whether a measured point lies within ``radius`` of each sight segment (sampled every radius)."""
    out = np.zeros(len(origins), dtype=bool)
    if not len(origins) or radius <= 0:
        return out
    length = np.linalg.norm(targets - origins, axis=1)
    steps = np.clip(np.ceil(length / radius).astype(np.int64), 1, 4000)
    # stop short of the sensor end: the sensor's own position holds no points, but its neighbourhood may
    ray = np.repeat(np.arange(len(origins)), steps)
    first = np.repeat(np.cumsum(steps) - steps, steps)
    t = (np.arange(len(ray)) - first + 0.5) / steps[ray]
    for s0 in range(0, len(ray), chunk):
        r, tt = ray[s0:s0 + chunk], t[s0:s0 + chunk]
        pts = origins[r] + tt[:, None] * (targets[r] - origins[r])
        d, _ = tree.query(pts, distance_upper_bound=radius, workers=-1)
        np.logical_or.at(out, r[np.isfinite(d)], True)
    return out


def confirmed_facets(items: list[tuple[Dataset, np.ndarray]]):  # -> (RaycastingScene, facet normals) | None
    """The reference facets the recent data matched, as one ray-casting scene (one geometry, so that Open3D's
    primitive ids index the stacked normals) with their normals."""
    tris = [ds.points[ds.faces[near]] for ds, near in items if near.any()]
    if not tris:
        return None
    soup = np.vstack(tris)
    scene = raycasting_scene([(soup.reshape(-1, 3), np.arange(3 * len(soup)).reshape(-1, 3))])
    return scene, np.vstack([ds.facet_normals(near) for ds, near in items if near.any()])


def blocked_by_confirmed(origins: np.ndarray, targets: np.ndarray, confirmed) -> np.ndarray:
    """Whether each sight segment passes through a confirmed facet from its front (a solid's far faces, seen from
    behind on the way out, do not count: closed CAD solids would otherwise cancel by parity)."""
    if confirmed is None or not len(origins):
        return np.zeros(len(origins), dtype=bool)
    scene, normals = confirmed
    ray, prim = segment_hits(scene, origins, targets)
    front = np.einsum("ij,ij->i", normals[prim], (targets - origins)[ray]) > 0
    return np.bincount(ray[front], minlength=len(origins)) > 0


@dataclass(frozen=True)
class Sight:
    """What may hide a reference element from a sensor: the recent surfaces (a ray-casting scene), the measured
    points of recent point clouds, the reference facets the recent data confirmed, and how sight rays are cast."""

    scene: Any  # o3d.t.geometry.RaycastingScene | None
    point_tree: cKDTree | None
    confirmed: Any  # (RaycastingScene, facet normals) | None, from confirmed_facets
    offset: float
    spacing: float
    rule: str


def hidden_from(pos: np.ndarray, target: np.ndarray, sight: Sight) -> np.ndarray:
    """Whether recent data, or a reference facet it confirmed, hides each element from its sight target (the sight
    ray starts ``offset`` towards the target, so that the element's own measured surface does not count)."""
    direction = target - pos
    length = np.linalg.norm(direction, axis=1, keepdims=True)
    start = pos + direction / np.maximum(length, 1e-12) * np.minimum(sight.offset, 0.5 * length)
    hidden = occluded(start, target, sight.scene, sight.rule)
    if sight.point_tree is not None:
        hidden |= shadowed(start, target, sight.point_tree, 1.5 * sight.spacing)
    # confirmed facets are exact geometry without noise: their rays start just off the element, so that a thin part
    # (a flange thinner than the offset measured surfaces need) still hides the face it covers
    near_start = pos + direction / np.maximum(length, 1e-12) * np.minimum(1e-3 * sight.offset, 0.5 * length)
    return hidden | blocked_by_confirmed(near_start, target, sight.confirmed)


def station_view(pos: np.ndarray, inside: np.ndarray, normal: np.ndarray | None, stations: list[Any],
                 sight: Sight, p: SightParams) -> np.ndarray:
    """In view from at least one station: inside its own volume, facing it, with a clear sight ray to it. Stations
    are tried in turn on the elements none has seen yet (a loop over the few stations; elements are vectorised)."""
    view = np.zeros(len(pos), dtype=bool)
    todo = np.flatnonzero(inside)
    for station in stations:  # _depth.Station: eye and its own volume
        if not todo.size:
            break
        eye = station.eye
        cand = todo[station.contains(pos[todo])]
        if p.cull_back_faces and normal is not None:
            cand = cand[np.einsum("ij,ij->i", normal[cand], eye[None, :] - pos[cand]) > 0]
        if p.occlusion and cand.size:
            cand = cand[~hidden_from(pos[cand], np.broadcast_to(eye, (cand.size, 3)), sight)]
        view[cand] = True
        todo = todo[~view[todo]]
    return view


def plane_view(pos: np.ndarray, inside: np.ndarray, normal: np.ndarray | None, vps: np.ndarray | None, sight: Sight,
               p: SightParams) -> tuple[np.ndarray, np.ndarray, int]:
    """In view by the Plane of Sight: inside the volume, facing a sensor, with a clear sight ray to the closest point
    of the POS. Returns the view, the elements inside once back faces are culled, and how many are occluded."""
    if p.cull_back_faces and normal is not None and vps is not None:
        # a facet facing away from every sensor was not seen, whatever lies between: a solid's far side
        inside = inside & np.any(np.einsum("fj,sfj->sf", normal, vps[:, None, :] - pos[None]) > 0, axis=0)
    view = inside.copy()
    idx = np.flatnonzero(inside)
    n_hidden = 0
    if p.occlusion and idx.size:
        pos_target = pos_closest(pos[idx], vps)
        hidden = hidden_from(pos[idx], pos_target, sight)
        view[idx[hidden]] = False
        n_hidden = int(hidden.sum())
    return view, inside, n_hidden
