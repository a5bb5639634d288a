"""Uncertainty-directed correspondences (paper Sec. 4.2.2, Fig. 5), vectorised.

- point → point: the reference points inside the query's 99 % ellipsoid of the combined uncertainty (a KD-tree
  ball search, then the exact Mahalanobis test per pair), merged into a Gaussian mixture that is compared with the
  query as one candidate;
- point → mesh: the first hit of a ray from the query along its most distinct uncertainty direction (largest
  eigenvector, both senses), and the closest point on the mesh (the natural choice for isotropic uncertainty), as
  separate candidates: the distance stage keeps the one with the lower change score;
- mesh → point and mesh → mesh: seeded random samples on each facet, in number proportional to its area, each
  treated as a point with the facet's uncertainty; the facet keeps the lowest score of its samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gdt_pipeline import Composite, Correspondences, Dataset, MixtureUncertainty
from gdt_pipeline.geometry import quad_inv3, triangle_points


@dataclass(frozen=True)
class Candidates:
    """Flat candidate arrays before they become a ``Correspondences``."""

    element: np.ndarray
    query_position: np.ndarray
    ref_item: np.ndarray
    ref_element: np.ndarray
    position: np.ndarray
    mixture: MixtureUncertainty | None = None


def default_density(ds: Dataset) -> float:
    """About four samples on an average facet of the dataset."""
    return 4.0 / max(float(ds.facet_areas().mean()), 1e-300)


_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser: a well-mixed 64-bit hash of each 64-bit value (wrapping arithmetic)."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def facet_uniforms(tri: np.ndarray, facet: np.ndarray, number: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Two uniforms in [0, 1) per sample, from a hash of its facet's corners, its number on the facet and the seed.

    Hand-rolled rather than a numpy Generator because a Generator's draws depend on which facets came before: these
    depend on the facet alone, so a tile holding some of the facets samples them exactly as the whole epoch does."""
    corners = np.ascontiguousarray(tri, dtype=np.float64).view(np.uint64).reshape(len(tri), 9)
    key = np.full(len(tri), np.uint64(seed % 2**64), dtype=np.uint64)
    for c in range(9):
        key = _mix(key ^ corners[:, c] ^ (_GOLDEN * np.uint64(c + 1)))
    base = key[facet] + number.astype(np.uint64) * _GOLDEN
    scale = 2.0 ** -53
    return ((_mix(base) >> np.uint64(11)).astype(np.float64) * scale,
            (_mix(base ^ np.uint64(0xD1B54A32D192ED03)) >> np.uint64(11)).astype(np.float64) * scale)


def query_samples(ds: Dataset, seed: int, density: float | None, max_per_facet: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Query points and the element each belongs to: the points themselves, or area-weighted facet samples
    (``density`` per unit², default about four on an average facet), each facet's drawn from its own hash."""
    if ds.faces is None:
        return ds.points, np.arange(len(ds.points))
    tri = ds.points[ds.faces]
    if density is None:
        density = default_density(ds)
    counts = np.clip(np.round(ds.facet_areas() * density).astype(np.int64), 1, max_per_facet)
    idx = np.repeat(np.arange(len(tri)), counts)
    number = np.arange(len(idx)) - np.repeat(np.cumsum(counts) - counts, counts)
    with np.errstate(over="ignore"):
        r1, r2 = facet_uniforms(tri, idx, number, seed)
    return triangle_points(tri, idx, r1, r2), idx


def sampling_covariance(pos: np.ndarray, cov: np.ndarray, neighbours: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Which points are sampled more sparsely than they are precise (largest σ under half the spacing s, their
    median distance to their three nearest neighbours), and for those the covariance of where the surface lies
    around them: (s/2)² in the tangent plane of their ``neighbours`` nearest points, none along its normal; on an
    edge or a corner, where those points fit no plane, (s/2)² in every direction."""
    if len(pos) < 4:
        return np.zeros(len(pos), dtype=bool), np.zeros((len(pos), 3, 3))
    k = min(neighbours, len(pos))
    tree = cKDTree(pos)
    out = np.zeros((len(pos), 3, 3))
    sparse = np.zeros(len(pos), dtype=bool)
    for s0 in range(0, len(pos), 200_000):  # chunks bound the (n, k, 3) neighbourhoods
        d, j = tree.query(pos[s0:s0 + 200_000], k=k, workers=-1)
        half = 0.5 * np.median(d[:, 1:4], axis=1)
        sp = np.linalg.eigvalsh(cov[s0:s0 + 200_000])[:, -1] < half**2
        nb = pos[j[sp]] - pos[j[sp]].mean(axis=1, keepdims=True)
        lam, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
        normal = vec[:, :, 0]
        flat = lam[:, 0] <= 0.01 * lam.sum(axis=1)  # surface variation: a plane, not an edge
        tangent = np.where(flat[:, None, None], np.eye(3)[None] - normal[:, :, None] * normal[:, None, :], np.eye(3))
        out[s0 + np.flatnonzero(sp)] = half[sp, None, None] ** 2 * tangent
        sparse[s0:s0 + 200_000] = sp
    return sparse, out


class ReferencePoints:
    """The visible points of a composite's point items, with their covariances, in one KD-tree; with ``sampling``,
    the covariance of points sampled more sparsely than they are precise also holds where the surface lies between
    them (``sampling_covariance``): a precise scan sampled every few millimetres still matches a later one whose
    points fall between its own."""

    def __init__(self, composite: Composite, sampling: bool = True) -> None:
        pos, item, elem, cov = [], [], [], []
        for i, it in enumerate(composite.items):
            ds = it.dataset
            if ds.faces is not None or not it.visible.any():
                continue
            vis = np.flatnonzero(it.visible)
            if ds.uncertainty is None:
                raise ValueError(f"reference dataset {ds.name!r} has no uncertainty")
            pos.append(ds.points[vis])
            item.append(np.full(len(vis), i))
            elem.append(vis)
            cov.append(np.asarray(ds.uncertainty.covariance(ds.n_elements))[vis])
        self.empty = not pos
        if self.empty:
            return
        self.pos, self.item, self.elem = np.concatenate(pos), np.concatenate(item), np.concatenate(elem)
        self.cov = np.concatenate(cov)
        self.sparse = np.zeros(len(self.pos), dtype=bool)
        if sampling:
            self.sparse, extra = sampling_covariance(self.pos, self.cov)
            self.cov = self.cov + extra
        self.origin = self.pos.mean(axis=0)
        # One search radius from the largest reference variance would make every query gather the whole scene
        # when a few grazing-angle ToF points have decimetre sigmas; tiers of similar variance (a factor of 4
        # apart) keep each search radius tight while still finding every point whose ellipsoid reaches the query.
        lam = np.linalg.eigvalsh(self.cov)[:, -1]
        # tiers on a fixed scale (not relative to the smallest variance here) are the same in every tile of an epoch
        tier = np.floor(np.log(np.maximum(lam, 1e-30)) / np.log(4.0)).astype(int)
        self.tiers = []
        for t in np.unique(tier):
            members = np.flatnonzero(tier == t)
            self.tiers.append((members, cKDTree(self.pos[members] - self.origin), float(lam[members].max())))
        self.max_var = float(lam.max())

    def neighbours(self, qpos: np.ndarray, lam_q: np.ndarray, chi2: float, pool: int
                   ) -> tuple[np.ndarray, np.ndarray]:
        """(query, reference) index pairs: per variance tier, the ``pool`` Euclidean-nearest within its 99 % bound.

        A fixed-size pool keeps the search in C and its cost bounded where decimetre-long ToF ellipsoids reach
        thousands of points; the Mahalanobis test after it is exact, and the mixture keeps the closest of these.
        """
        fq, fr = [], []
        for members, tree, var in self.tiers:
            k = min(pool, len(members))
            radius = np.sqrt(chi2 * (lam_q + var))
            dist, idx = tree.query(qpos - self.origin, k=k, distance_upper_bound=float(radius.max()),
                                   workers=-1)
            dist, idx = dist.reshape(len(qpos), k), idx.reshape(len(qpos), k)
            ok = dist <= radius[:, None]
            fq.append(np.nonzero(ok)[0])
            fr.append(members[idx[ok]])
        if not fq:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(fq), np.concatenate(fr)


def point_to_point(qpos: np.ndarray, qcov: np.ndarray, ref: ReferencePoints, chi2: float, max_components: int,
                   element: np.ndarray) -> Candidates:
    """One mixture candidate per query that has reference points inside its combined 99 % ellipsoid."""
    lam_q = np.linalg.eigvalsh(qcov)[:, -1]
    flat_q, flat_r = ref.neighbours(qpos, lam_q, chi2, 4 * max_components)
    d = ref.pos[flat_r] - qpos[flat_q]
    m2 = quad_inv3(qcov[flat_q] + ref.cov[flat_r], d)
    keep = m2 <= chi2
    flat_q, flat_r, m2 = flat_q[keep], flat_r[keep], m2[keep]
    order = np.lexsort((m2, flat_q))
    flat_q, flat_r, m2 = flat_q[order], flat_r[order], m2[order]
    starts = np.r_[0, np.flatnonzero(np.diff(flat_q)) + 1]
    rank = np.arange(len(flat_q)) - np.repeat(starts, np.diff(np.r_[starts, len(flat_q)]))
    # a sparse precise point already stands for the surface around it: its neighbours would only smear it (and
    # make the mixture's BC expensive to bound), so it is its query's one component
    first = np.repeat(flat_r[starts], np.diff(np.r_[starts, len(flat_q)])) if len(flat_q) else flat_r
    top = (rank < max_components) & ~(ref.sparse[first] & (rank > 0))
    flat_q, flat_r, rank = flat_q[top], flat_r[top], rank[top]
    queries = np.unique(flat_q)
    if queries.size == 0:
        z = np.zeros(0, dtype=np.int64)
        return Candidates(z, np.zeros((0, 3)), z, z, np.zeros((0, 3)), None)
    row = np.searchsorted(queries, flat_q)
    k = int(rank.max()) + 1
    n = len(queries)
    weights = np.zeros((n, k))
    weights[row, rank] = 1.0
    weights /= weights.sum(axis=1, keepdims=True)
    comp_pos = np.zeros((n, k, 3))
    comp_pos[row, rank] = ref.pos[flat_r]
    centre = np.einsum("nk,nki->ni", weights, comp_pos)
    means = np.where(weights[..., None] > 0, comp_pos - centre[:, None, :], 0.0)
    covs = np.broadcast_to(np.eye(3), (n, k, 3, 3)).copy()  # placeholders for zero-weight slots
    covs[row, rank] = ref.cov[flat_r]
    nearest = flat_r[rank == 0]  # the lowest-Mahalanobis neighbour names the matched element
    return Candidates(element=element[queries], query_position=qpos[queries], ref_item=ref.item[nearest],
                      ref_element=ref.elem[nearest], position=centre,
                      mixture=MixtureUncertainty(weights, means, covs))


class ReferenceMeshes:
    """The visible facets of a composite's mesh items in one Open3D raycasting scene (float32 near the origin)."""

    def __init__(self, composite: Composite) -> None:
        import open3d as o3d

        self.items: list[tuple[int, np.ndarray]] = []
        geoms = []
        lows, highs = [], []
        for i, it in enumerate(composite.items):
            ds = it.dataset
            if ds.faces is None or not it.visible.any():
                continue
            vis = np.flatnonzero(it.visible)
            self.items.append((i, vis))
            geoms.append((ds.points, ds.faces[vis]))
            lows.append(ds.points.min(axis=0))
            highs.append(ds.points.max(axis=0))
        self.empty = not geoms
        if self.empty:
            return
        self.origin = (np.min(lows, axis=0) + np.max(highs, axis=0)) / 2
        self.scene = o3d.t.geometry.RaycastingScene()
        for verts, faces in geoms:
            self.scene.add_triangles(o3d.core.Tensor((verts - self.origin).astype(np.float32)),
                                     o3d.core.Tensor(faces.astype(np.uint32)))
        self.item_of_geom = np.array([i for i, _ in self.items], dtype=np.int64)

    def _map(self, gid: np.ndarray, pid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        item = self.item_of_geom[gid]
        elem = np.empty(len(gid), dtype=np.int64)
        for g in np.unique(gid):
            sel = gid == g
            elem[sel] = self.items[g][1][pid[sel]]
        return item, elem


def point_to_mesh(qpos: np.ndarray, qcov: np.ndarray, ref: ReferenceMeshes, search_sigmas: float, extra_var: float,
                  element: np.ndarray) -> Candidates:
    """Candidates from rays along each query's largest uncertainty axis (both senses) and from the closest point."""
    import open3d as o3d

    w, v = np.linalg.eigh(qcov)
    axis = v[:, :, -1]
    reach = search_sigmas * np.sqrt(w[:, -1] + extra_var)
    q = (qpos - ref.origin).astype(np.float32)
    parts = []
    for sense in (1.0, -1.0):
        rays = np.hstack([q, (sense * axis).astype(np.float32)])
        ans = ref.scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        ok = np.isfinite(t) & (t <= reach)
        idx = np.flatnonzero(ok)
        item, elem = ref._map(ans["geometry_ids"].numpy()[ok].astype(np.int64),
                              ans["primitive_ids"].numpy()[ok].astype(np.int64))
        parts.append((idx, item, elem, qpos[idx] + sense * axis[idx] * t[ok, None]))
    ans = ref.scene.compute_closest_points(o3d.core.Tensor(q))
    pts = ans["points"].numpy().astype(np.float64) + ref.origin
    ok = np.linalg.norm(pts - qpos, axis=1) <= reach
    idx = np.flatnonzero(ok)
    item, elem = ref._map(ans["geometry_ids"].numpy()[ok].astype(np.int64),
                          ans["primitive_ids"].numpy()[ok].astype(np.int64))
    parts.append((idx, item, elem, pts[ok]))
    idx = np.concatenate([p[0] for p in parts])
    return Candidates(element=element[idx], query_position=qpos[idx], ref_item=np.concatenate([p[1] for p in parts]),
                      ref_element=np.concatenate([p[2] for p in parts]),
                      position=np.concatenate([p[3] for p in parts]))


def to_correspondences(query: int, n_elements: int, parts: list[Candidates], method: str) -> Correspondences:
    """Merge candidate sets (at most one of them with mixtures) into one ``Correspondences``."""
    parts = [p for p in parts if len(p.element)]
    if not parts:
        z = np.zeros(0, dtype=np.int64)
        return Correspondences(query, z, z, np.zeros((0, 3)), np.zeros(0), method, element=z,
                               query_position=np.zeros((0, 3)), n_elements=n_elements)
    mixtures = [p for p in parts if p.mixture is not None]
    if len(mixtures) > 1:
        raise ValueError("internal: at most one set of mixture candidates can be merged")
    element = np.concatenate([p.element for p in parts])
    qpos = np.concatenate([p.query_position for p in parts])
    pos = np.concatenate([p.position for p in parts])
    ref_row = None
    if mixtures:
        # mixture candidates point at their own row; the others (facets) use their element's uncertainty
        ref_row = np.concatenate([np.arange(len(p.element)) if p.mixture is not None
                                  else np.full(len(p.element), -1) for p in parts])
    return Correspondences(query, np.concatenate([p.ref_item for p in parts]),
                           np.concatenate([p.ref_element for p in parts]), pos,
                           np.linalg.norm(qpos - pos, axis=1), method, element=element, query_position=qpos,
                           ref_uncertainty=mixtures[0].mixture if mixtures else None, n_elements=n_elements,
                           ref_row=ref_row)
