"""Where the reference has data: what tells a recent element without a correspondence "new" from "not comparable".

An element with nothing within reach is new only where the reference covers its place, so that something there
would have been compared had it been there before:

- a reference **mesh** covers every place whose closest point on it lies inside its surface, not on its rim (an
  edge only one visible facet uses): a closed CAD part covers all space around it, an open scan mesh only what lies
  over it;
- a reference **point cloud** covers the places within its own sampling: the nearest reference point lies within
  the element's 99 % region plus ``COVER_SPACINGS`` times the reference's spacing there (the distance from that
  point to its ``SPACING_NEIGHBOURS``-th neighbour). A strip that an earlier flight never reached, or the far side
  of an object an earlier scan never saw, is not covered.

Elsewhere the element is not comparable: the twin had nothing there to compare it with.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from .geometry import raycasting_scene
from .types import Composite, CompositeItem
from .types.region99 import CHI2_3_99

COVER_SPACINGS = 3.0
SPACING_NEIGHBOURS = 4
# a closest point within this barycentric distance of a rim edge lies on it (Open3D clamps onto the edge in float32)
ON_EDGE = 1e-4


class Coverage(NamedTuple):
    """Per query point: whether the reference covers its place, and how far from it the test looked."""

    covered: np.ndarray
    looked: np.ndarray


def rim_edges(faces: np.ndarray) -> np.ndarray:
    """Per facet ``(F,3)``, whether the edge opposite each corner is used by this facet only (a rim)."""
    f = np.asarray(faces, dtype=np.int64)
    edges = np.sort(np.concatenate([f[:, [1, 2]], f[:, [2, 0]], f[:, [0, 1]]]), axis=1)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    return np.asarray((counts[inverse.ravel()] == 1).reshape(3, -1).T)


def _visible_facets(items: list[CompositeItem]) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
    meshes, rims = [], []
    for it in items:
        faces = np.asarray(it.dataset.faces)[it.visible]
        if len(faces):
            meshes.append((np.asarray(it.dataset.points), faces))
            rims.append(rim_edges(faces))
    return meshes, (np.concatenate(rims) if rims else np.zeros((0, 3), bool))


class ReferenceCoverage:
    """The coverage test against one reference, its ray-casting scene and kd-tree built once, on first use (a
    distance stage asks for every recent dataset of the epoch)."""

    def __init__(self, reference: Composite) -> None:
        self.meshes = [it for it in reference.items if it.dataset.faces is not None and it.visible.any()]
        clouds = [np.asarray(it.dataset.points)[it.visible] for it in reference.items
                  if it.dataset.faces is None and it.visible.any()]
        self.cloud = np.concatenate(clouds) if clouds else np.zeros((0, 3))
        self._scene: Any = None
        self._rims = np.zeros((0, 3), bool)
        self._tree: cKDTree | None = None

    def on_meshes(self, points: np.ndarray) -> Coverage:
        """Whether each point's closest point on the visible reference facets lies inside their surface (not on a
        rim)."""
        import open3d as o3d

        if not self.meshes or not len(points):
            return Coverage(np.zeros(len(points), bool), np.zeros(len(points)))
        if self._scene is None:
            meshes, self._rims = _visible_facets(self.meshes)
            self._scene = raycasting_scene(meshes)
        found = self._scene.compute_closest_points(o3d.core.Tensor(np.asarray(points, dtype=np.float32)))
        uv = found["primitive_uvs"].numpy().astype(np.float64)
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        on_rim = ((bary < ON_EDGE) & self._rims[found["primitive_ids"].numpy().astype(np.int64)]).any(axis=1)
        return Coverage(~on_rim, np.linalg.norm(found["points"].numpy() - points, axis=1))

    def on_clouds(self, points: np.ndarray, scale: np.ndarray) -> Coverage:
        """Whether each point lies within the visible reference points' own sampling (the module's docstring)."""
        if len(self.cloud) <= SPACING_NEIGHBOURS or not len(points):
            return Coverage(np.zeros(len(points), bool), np.zeros(len(points)))
        if self._tree is None:
            self._tree = cKDTree(self.cloud)
        return sampled(self.cloud, points, scale, tree=self._tree)

    def __call__(self, points: np.ndarray, scale: np.ndarray) -> Coverage:
        """Whether some visible reference item covers each of ``points`` (``scale``: each one's 99 % radius)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        by_mesh, by_cloud = self.on_meshes(points), self.on_clouds(points, scale)
        looked = np.maximum(np.where(by_mesh.covered, by_mesh.looked, 0.0), by_cloud.looked)
        return Coverage(by_mesh.covered | by_cloud.covered, looked)


def sampled(cloud: np.ndarray, points: np.ndarray, scale: np.ndarray, spacings: float = COVER_SPACINGS,
            tree: cKDTree | None = None) -> Coverage:
    """Whether each point lies within ``cloud``'s own sampling: its nearest cloud point no farther than ``scale``
    plus ``spacings`` times the cloud's spacing there (``tree``: a kd-tree of ``cloud`` already built)."""
    if len(cloud) <= SPACING_NEIGHBOURS or not len(points):
        return Coverage(np.zeros(len(points), bool), np.zeros(len(points)))
    tree = cKDTree(cloud) if tree is None else tree
    d, nearest = tree.query(points, workers=-1)
    spacing = tree.query(cloud[nearest], k=SPACING_NEIGHBOURS + 1, workers=-1)[0][:, -1]
    return Coverage(d <= scale + spacings * spacing, d + spacing)


def reference_coverage(reference: Composite, points: np.ndarray, scale: np.ndarray) -> Coverage:
    """Whether some visible reference item covers each of ``points`` (``scale``: each one's 99 % radius)."""
    return ReferenceCoverage(reference)(points, scale)


def within_pair_region(points: np.ndarray, cov: np.ndarray, cloud: np.ndarray, cloud_cov: np.ndarray,
                       tree: cKDTree | None = None) -> np.ndarray:
    """Whether each point's nearest ``cloud`` point lies within the pair's 99 % region (Mahalanobis distance under
    the sum of both covariances, χ²₃ at 0.99): the two measured the same place (``tree``: of ``cloud``, if built)."""
    if not len(cloud) or not len(points):
        return np.zeros(len(points), bool)
    _, nearest = (cKDTree(cloud) if tree is None else tree).query(points, workers=-1)
    d = cloud[nearest] - points
    total = cov + cloud_cov[nearest] + 1e-30 * np.eye(3)
    return np.asarray(np.einsum("ni,ni->n", d, np.linalg.solve(total, d[:, :, None])[:, :, 0]) <= CHI2_3_99)
