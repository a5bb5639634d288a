"""Contact faces: reference facets that touch another closed part (a frame web's face under its flange, a cabinet's
base on the floor) can never be seen, whatever the scan shows around them. A sample is on such a face when the point
just outside it, along its facet's outward normal, lies inside an intact closed part of the reference."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..geometry import raycasting_scene
from ..types import Composite


def is_closed(faces: np.ndarray) -> bool:
    """Whether every edge of a triangle mesh is shared by exactly two of its facets (a closed surface)."""
    if not len(faces):
        return False
    edges = np.sort(np.vstack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def closed_parts(reference: Composite) -> list[Any]:
    """One ray-casting scene per intact closed mesh of the reference (every facet still visible): the solids that
    can cover another part's face. Separate scenes, so that two touching parts do not cancel each other's parity."""
    return [raycasting_scene([(it.dataset.points, it.dataset.faces)]) for it in reference.items
            if it.dataset.faces is not None and it.visible.all() and is_closed(it.dataset.faces)]


def in_contact(pos: np.ndarray, normals: np.ndarray, parts: list[Any], step: float, owner: np.ndarray | None = None,
               chunk: int = 500_000) -> np.ndarray:
    """Whether the point ``step`` outside each sample (along its facet's outward normal) lies inside a closed part.
    ``normals`` per sample, or per facet with ``owner`` giving each sample's facet; the probes go to Open3D a chunk
    at a time (three million samples' probes and normals were 260 MB at once)."""
    import open3d as o3d

    out = np.zeros(len(pos), dtype=bool)
    if not parts or not len(pos):
        return out
    for s0 in range(0, len(pos), chunk):
        part = slice(s0, s0 + chunk)
        nrm = normals[part] if owner is None else normals[owner[part]]
        unit = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        probe = o3d.core.Tensor((pos[part] + step * unit).astype(np.float32))
        for scene in parts:
            out[part] |= scene.compute_occupancy(probe).numpy().astype(bool)
    return out
