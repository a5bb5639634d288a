"""Normals of point clouds."""

from __future__ import annotations

import numpy as np


def estimate_normals(points: np.ndarray, neighbours: int, origin: np.ndarray | tuple | None = None) -> np.ndarray:
    """Unit normals of a point cloud from its k nearest neighbours (Open3D's PCA normals), computed about ``origin``
    (default: the points' mean; pass the epoch's to get the same normals from any subset holding the neighbours)."""
    import open3d as o3d

    origin = points.mean(axis=0) if origin is None else np.asarray(origin, dtype=np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points - origin))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=neighbours))
    return np.asarray(pcd.normals)


def knn_reach(points: np.ndarray, neighbours: int) -> np.ndarray:
    """Per point, the distance to its ``neighbours``-th nearest point (itself included, as Open3D counts): how far
    a k-nearest neighbourhood reached."""
    from scipy.spatial import cKDTree

    k = min(neighbours, len(points))
    if k == 0:
        return np.zeros(0)
    dist, _ = cKDTree(points).query(points, k=[k], workers=-1)
    return dist[:, 0]
