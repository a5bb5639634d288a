"""Normals of point clouds."""

from __future__ import annotations

import numpy as np


def estimate_normals(points: np.ndarray, neighbours: int) -> np.ndarray:
    """Unit normals of a point cloud from its k nearest neighbours (Open3D's PCA normals)."""
    import open3d as o3d

    origin = points.mean(axis=0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points - origin))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=neighbours))
    return np.asarray(pcd.normals)
