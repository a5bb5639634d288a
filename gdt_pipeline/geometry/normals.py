"""Normals of point clouds, and how far their k-nearest neighbourhoods reached."""

from __future__ import annotations

import numpy as np

# Cells of a proof grid beyond this many (per axis product) would overflow the packed cell key: no proof then.
_MAX_CELLS = 2 ** 62


def estimate_normals(points: np.ndarray, neighbours: int, origin: np.ndarray | tuple | None = None) -> np.ndarray:
    """Unit normals of a point cloud from its k nearest neighbours (Open3D's PCA normals), computed about ``origin``
    (default: the points' mean; pass the epoch's to get the same normals from any subset holding the neighbours)."""
    import open3d as o3d

    origin = points.mean(axis=0) if origin is None else np.asarray(origin, dtype=np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points - origin))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=neighbours))
    return np.asarray(pcd.normals)


def knn_reach(points: np.ndarray, neighbours: int, which: np.ndarray | None = None) -> np.ndarray:
    """Per point (of ``which``, default all), the distance to its ``neighbours``-th nearest point (itself included,
    as Open3D counts): how far a k-nearest neighbourhood reached."""
    from scipy.spatial import cKDTree

    k = min(neighbours, len(points))
    queries = points if which is None else points[which]
    if k == 0 or len(queries) == 0:
        return np.zeros(len(queries))
    dist, _ = cKDTree(points).query(queries, k=[k], workers=-1)
    return dist[:, 0]


def within_dense_cells(points: np.ndarray, neighbours: int, cell: float, lower: np.ndarray) -> np.ndarray:
    """Per point, whether its cube of a grid of side ``cell`` (from ``lower``) holds at least ``neighbours`` points
    (itself included): then its k-nearest neighbourhood reaches at most the cube's diagonal, cell·√3.

    This proves most points' reach in one sort instead of a second k-nearest search (sensor_model searched every
    neighbourhood twice in tiles: once for the normals in Open3D, which does not return the distances, once here).
    """
    n = len(points)
    if n == 0 or not np.isfinite(cell) or cell <= 0:
        return np.zeros(n, dtype=bool)
    ijk = np.floor((points - lower) / cell).astype(np.int64)
    ijk -= ijk.min(axis=0)
    dims = ijk.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) >= _MAX_CELLS:
        return np.zeros(n, dtype=bool)
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    return counts[inverse] >= neighbours
