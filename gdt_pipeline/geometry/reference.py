"""Vectorised geometric queries shared by stages: nearest reference elements of a composite (points and facets)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..types import Composite


@dataclass(frozen=True)
class NearestResult:
    """Per query: the matched composite item (-1: none), element within it, matched position and distance."""

    item: np.ndarray
    element: np.ndarray
    position: np.ndarray
    distance: np.ndarray


class ReferenceIndex:
    """Search structures over the visible elements of a composite: a KD-tree of points, a raycasting scene of facets.

    Open3D works in float32, so coordinates are taken relative to a local origin (the reference's bounding-box
    centre); otherwise georeferenced data (UTM metres ~1e6) would lose centimetres.
    """

    def __init__(self, composite: Composite) -> None:
        pts_items, pts_elems, pts = [], [], []
        self._mesh_items: list[tuple[int, np.ndarray]] = []
        mesh_geoms: list[tuple[np.ndarray, np.ndarray]] = []
        lows, highs = [], []
        for i, item in enumerate(composite.items):
            ds = item.dataset
            vis = np.flatnonzero(item.visible)
            if vis.size == 0:
                continue
            lows.append(ds.points.min(axis=0))
            highs.append(ds.points.max(axis=0))
            if ds.faces is None:
                pts_items.append(np.full(vis.size, i, dtype=np.int64))
                pts_elems.append(vis)
                pts.append(ds.points[vis])
            else:
                self._mesh_items.append((i, vis))
                mesh_geoms.append((ds.points, ds.faces[vis]))
        self.origin = (np.min(lows, axis=0) + np.max(highs, axis=0)) / 2 if lows else np.zeros(3)
        self._tree = None
        if pts:
            self._pt_item = np.concatenate(pts_items)
            self._pt_elem = np.concatenate(pts_elems)
            self._pt_pos = np.concatenate(pts)
            self._tree = cKDTree(self._pt_pos - self.origin)
        self._scene = None
        if mesh_geoms:
            import open3d as o3d  # heavy; only when the reference holds meshes

            self._scene = o3d.t.geometry.RaycastingScene()
            for verts, faces in mesh_geoms:
                self._scene.add_triangles(o3d.core.Tensor((verts - self.origin).astype(np.float32)),
                                          o3d.core.Tensor(faces.astype(np.uint32)))

    @property
    def empty(self) -> bool:
        """True when the composite has no visible element to match against."""
        return self._tree is None and self._scene is None

    def nearest(self, queries: np.ndarray, max_distance: float | None = None) -> NearestResult:
        """Closest visible reference element of each query point (a point, or the closest point on a facet)."""
        q = np.asarray(queries, dtype=np.float64) - self.origin
        n = len(q)
        item = np.full(n, -1, dtype=np.int64)
        elem = np.full(n, -1, dtype=np.int64)
        pos = np.full((n, 3), np.nan)
        dist = np.full(n, np.inf)
        if self._tree is not None and n:
            d, j = self._tree.query(q, k=1, distance_upper_bound=np.inf if max_distance is None else max_distance,
                                          workers=-1)
            ok = np.isfinite(d)
            item[ok], elem[ok], dist[ok] = self._pt_item[j[ok]], self._pt_elem[j[ok]], d[ok]
            pos[ok] = self._pt_pos[j[ok]]
        if self._scene is not None and n:
            import open3d as o3d

            ans = self._scene.compute_closest_points(o3d.core.Tensor(q.astype(np.float32)))
            mpos = ans["points"].numpy().astype(np.float64)
            gid = ans["geometry_ids"].numpy().astype(np.int64)
            pid = ans["primitive_ids"].numpy().astype(np.int64)
            md = np.linalg.norm(mpos - q, axis=1)
            better = md < dist
            if max_distance is not None:
                better &= md <= max_distance
            if better.any():
                g = gid[better]
                items = np.array([it for it, _ in self._mesh_items], dtype=np.int64)
                item[better] = items[g]
                # primitive ids index the visible-facet subset that was added for that geometry
                offsets = [vis for _, vis in self._mesh_items]
                elem_b = np.empty(int(better.sum()), dtype=np.int64)
                for gi in np.unique(g):
                    sel = g == gi
                    elem_b[sel] = offsets[gi][pid[better][sel]]
                elem[better] = elem_b
                pos[better] = mpos[better] + self.origin
                dist[better] = md[better]
        found = item >= 0
        dist[~found] = np.nan
        return NearestResult(item=item, element=elem, position=pos, distance=dist)

