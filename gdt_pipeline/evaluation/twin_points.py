"""A twin's element sets as points: an epoch read back as a composite, and its sets as points (meshes sampled)."""

from __future__ import annotations

import numpy as np

from twin_store import TwinStore

from ..types import Composite, CompositeItem, Dataset


def composite_from_twin(store: TwinStore, epoch: str) -> Composite:
    """The twin's composite of an epoch, as the fusion stage left it."""
    items = []
    for es in store.read_epoch(epoch):
        ds = Dataset(es.key, "as-is", es.points, faces=es.faces)
        items.append(CompositeItem(es.key, ds, epoch, es.state, es.score.astype(np.float64), es.source_epoch,
                                   es.visible))
    return Composite(tuple(items))


def sample_sets(sets: list, spacing: float, rng: np.random.Generator, *, visible_only: bool = True,
                facing: np.ndarray | None = None) -> np.ndarray:
    """Points of the given element sets: point sets as they are, meshes sampled at ``spacing``; with ``facing``
    (station positions), only facets that face one of them, as a scanner would have seen the part."""
    import trimesh

    out = []
    for es in sets:
        keep = es.visible.astype(bool) if visible_only else np.ones(es.n_elements, bool)
        if es.kind == "mesh" and facing is not None and keep.any():
            tri = es.points[es.faces]
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            centre = tri.mean(axis=1)
            keep &= np.any(np.einsum("fj,sfj->sf", normal, facing[:, None, :] - centre[None]) > 0, axis=0)
        if not keep.any():
            continue
        if es.kind == "points":
            out.append(es.points[keep])
            continue
        mesh = trimesh.Trimesh(es.points, es.faces[keep], process=False)
        n = max(int(mesh.area / spacing**2), 1)
        pts, _ = trimesh.sample.sample_surface(mesh, n, seed=int(rng.integers(2**31)))
        out.append(np.asarray(pts))
    return np.vstack(out) if out else np.zeros((0, 3))
