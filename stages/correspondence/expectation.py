"""Neighbourhood expectation (paper Sec. 3: "estimating the expectation values of points lying on the objects'
surfaces is necessary"): each point of a dense noisy cloud is judged through the expectation of the surface it
lies on, not through its own noisy position.

Per point P with covariance Σ:

1. its anchor H on the twin's meshes. With a station: where the beam through P first meets a facet facing the
   station within the search reach (a beam cannot have passed through a surface it faces; the nearest crossing
   would move points far behind a thin part onto the floor behind it). Without one: the nearest crossing along
   Σ's largest axis, or the closest point where Σ has no dominant axis. n is the facet's normal;
2. its offset along that normal, δ = (P − H)·n, with variance nᵀΣn. Offsets are taken against the twin's own
   shape, so its bends, edges and thin parts do not bias them;
3. its neighbours: up to ``neighbours`` points whose anchors lie within ``radius`` of H (default: the radius of
   P's own 99 % region) on facets facing within 60° of n; in the first pass from P's own dataset (station) only,
   in the second from every recent point dataset where the first pass's expectations agree within 3 σ (a new
   part's points are anchored where their beams meet the twin behind it, often on floor another station sees
   directly: the two must not pool);
4. the pooled offset, in each quadrant about H apart: the mean of the nearest 2, 4, 8, … neighbours' offsets
   (equal weights: a scanner's σ grows with the measured range, and inverse-variance weights would pull the mean
   towards the sensor), leaving out those more than 3.5 σ off the median of the nearest 32 (another surface).
   The scale is chosen by the intersection of confidence intervals (Katkovnik's LPA-ICI): the largest whose
   interval (± ``gamma`` σ) still meets all smaller ones'. The quadrants and the point itself are fused by
   inverse variance; where a quadrant runs into a change's edge its estimates drift, it stops early and weighs
   little. Where the members scatter about their quadrants' means more than their σ promise (χ²/dof > 1: two
   surfaces mixed, a bend), the pooled variance grows by that factor. A point that is itself more than 3.5 σ off
   its neighbours' median lies on another surface: it keeps its own value;
5. a second pass anchors each point on the crossing of its beam nearest to where its neighbours put the surface
   (two surfaces within the noise along one beam: one point cannot tell which it is on, its neighbours can) and
   pools again, now across stations;
6. the expectation: the point on P's line (its beam) at the pooled offset; its covariance is the pooled variance
   along n and, across n, that of a point on the line (Σ across the line, the pooled variance over cos² along
   it), so its spread along the surface shrinks with the pooling too.

A point with no anchor within the search reach, a mesh's facets, or a point with fewer than 8 neighbours keeps
its own position and covariance (the per-point test): pooling needs a known surface and a dense cloud.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from gdt_pipeline import Dataset, GaussianUncertainty, StageContext
from gdt_pipeline.geometry import line_crossings
from gdt_pipeline.names import UNITS

from .pooling_kernel import pool_rows

MIN_NEIGHBOURS = 8  # fewer pooled: the point keeps its own value
MIN_COS = 0.05
COS_CONE = 0.5  # neighbours facing within 60°: a plate's two faces and a box's sides never mix
TRIM_SIGMAS = 3.5  # neighbours farther than this off the median of the nearest CENTRE are another surface
CENTRE = 32  # a median of 8 is off by 0.44 σ, which shifts the trimming window and adds to the mean's variance
ISOTROPIC_RATIO = 2.0  # largest / second variance below this: no dominant axis, the closest point anchors
REGION_99 = 11.345  # χ²(3) at 0.99: the squared radius, in σ, of a point's 99 % region
# a point of another dataset (station) pools only where the two first-pass expectations agree within this many σ:
# a new part's points are anchored where their beams meet the twin behind it, often on floor another station sees
# directly; pooled together, the part's offsets pulled that floor's expectations up (0.6-0.8 σ within 5 cm of
# parts on the ToF family) and the floor's pulled the part's down
GATE_SIGMAS = 3.0
CHUNK = 8192  # queries pooled at a time: bounds the kd-tree's (chunk × neighbours) answer to 33 MB at 256


@dataclass(frozen=True)
class Anchors:
    """Per point: its anchor on the twin's meshes, the normal there, its offset along the normal and the variance
    of that offset (``ok`` False where no anchor lies within reach)."""

    anchor: np.ndarray
    normal: np.ndarray
    offset: np.ndarray
    variance: np.ndarray
    ok: np.ndarray
    axis: np.ndarray
    largest: np.ndarray  # the largest variance of the point's covariance


@dataclass(frozen=True)
class Expectation:
    """Per point of one dataset: its expected position and covariance, and how many neighbours were pooled
    (1: its own)."""

    position: np.ndarray
    covariance: np.ndarray
    pooled: np.ndarray


@dataclass(frozen=True)
class Lines:
    """Per point of one dataset, the line its offset is taken along and where that line crosses the twin's meshes
    within reach, cast once for both passes: the crossings (``ray``: the point, ``along``: point minus crossing
    along the line, ``normal``: the facet's) and, for points with no dominant axis, their closest points
    (``closest_rows``, ``closest``, ``closest_normal``, ``closest_distance``)."""

    pos: np.ndarray
    cov: np.ndarray
    axis: np.ndarray
    largest: np.ndarray
    facing: bool
    ray: np.ndarray
    along: np.ndarray
    normal: np.ndarray
    closest_rows: np.ndarray
    closest: np.ndarray
    closest_normal: np.ndarray

    def crossings(self) -> tuple[np.ndarray, np.ndarray]:
        """Every place the lines meet the meshes within reach (closest points included) and the point it belongs
        to; a closest point out of reach is not one."""
        where = np.concatenate([self.pos[self.ray] - self.axis[self.ray] * self.along[:, None], self.closest])
        owner = np.concatenate([self.ray, self.closest_rows])
        found = np.isfinite(where[:, 0])
        return where[found], owner[found]


def cast_lines(scene: object, origin: np.ndarray, normals: list[np.ndarray], pos: np.ndarray, cov: np.ndarray,
               station: np.ndarray | None, reach_sigmas: float) -> Lines:
    """Each point's line and its crossings with the meshes of ``scene`` (an Open3D raycasting scene about
    ``origin``; ``normals``: each geometry's facet normals) within ``reach_sigmas`` σ: with a station its beam,
    crossings only with facets facing the station; without, Σ's largest axis, or the closest point when Σ has no
    dominant axis."""
    import open3d as o3d

    w, v = np.linalg.eigh(cov)
    reach = reach_sigmas * np.sqrt(w[:, -1])
    if station is not None:
        axis = pos - station
        axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-300)
    else:
        axis = v[:, :, -1].copy()
    ray, along, n = line_crossings(scene, normals, pos - origin, axis, reach)
    ok = np.ones(len(ray), dtype=bool)
    if station is not None:  # the side a sensor looking along the beam sees
        ok &= np.einsum("ij,ij->i", n, axis[ray]) < 0
    rows = np.flatnonzero(w[:, -1] < ISOTROPIC_RATIO * w[:, -2]) if station is None else np.zeros(0, np.int64)
    closest, closest_normal = np.zeros((len(rows), 3)), np.zeros((len(rows), 3))
    if len(rows):
        near = scene.compute_closest_points(o3d.core.Tensor((pos[rows] - origin).astype(np.float32)))
        closest = near["points"].numpy().astype(np.float64) + origin
        closest_normal = near["primitive_normals"].numpy().astype(np.float64)
        far = np.linalg.norm(closest - pos[rows], axis=1) > reach[rows]
        closest[far] = np.nan
        axis[rows] = closest_normal  # the closest point lies along the normal: the line the offset moves on
    return Lines(pos, cov, axis, w[:, -1], station is not None, ray[ok], along[ok], n[ok], rows, closest,
                 closest_normal)


def surface_anchors(lines: Lines, target: np.ndarray | None = None) -> Anchors:
    """Each point's anchor: of its line's crossings, the one nearest to ``target`` (a distance along the line back
    from the point); without a target the first a beam meets, or without a station the nearest to the point."""
    ray, along = lines.ray, lines.along
    # seen from a station, the first facing crossing: the nearest to the point would move points far behind a thin
    # part onto the floor behind it, cut one tail of the part's offsets and bias their mean towards the sensor
    key = -along if target is None and lines.facing else np.abs(along - (0.0 if target is None else target[ray]))
    order = np.lexsort((key, ray))
    first = order[np.r_[True, ray[order][1:] != ray[order][:-1]]] if len(order) else order
    pos = lines.pos
    dist = np.full(len(pos), np.inf)
    normal = np.zeros_like(pos)
    dist[ray[first]], normal[ray[first]] = along[first], lines.normal[first]
    anchor = pos - lines.axis * np.where(np.isfinite(dist), dist, 0.0)[:, None]
    rows = lines.closest_rows
    if len(rows):
        found = np.isfinite(lines.closest[:, 0])
        dist[rows] = np.where(found, 0.0, np.inf)
        anchor[rows], normal[rows] = np.where(found[:, None], lines.closest, pos[rows]), lines.closest_normal
    ok = np.isfinite(dist)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    offset = np.einsum("ij,ij->i", pos - anchor, normal)
    variance = np.einsum("ni,nij,nj->n", normal, lines.cov, normal)
    return Anchors(anchor, normal, np.where(ok, offset, 0.0), variance, ok, lines.axis, lines.largest)


@dataclass(frozen=True)
class PoolingParams:
    """How far pooling reaches: at most ``neighbours`` points whose anchors lie within ``radius`` (twin units;
    None: the radius of each point's own 99 % region along its largest axis),
    scales chosen with intervals of ± ``gamma`` σ; anchors within ``reach_sigmas`` σ of their point."""

    neighbours: int
    radius: float | None
    gamma: float
    reach_sigmas: float


def _safe_cos(cos: np.ndarray) -> np.ndarray:
    """A line's cosine to a normal, kept off zero (a line along the surface meets it nowhere in particular)."""
    return np.where(np.abs(cos) < MIN_COS, np.copysign(MIN_COS, cos), cos)


def _pool(found: list[Anchors], params: PoolingParams, earlier: tuple[np.ndarray, np.ndarray] | None = None,
          wanted: np.ndarray | None = None, start: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point of all datasets: the pooled offset along its normal, its variance and the neighbours pooled. Without
    ``earlier`` (offsets and variances of a first pass) each point pools within its own dataset; with it, points of
    other datasets join where their earlier expectations agree within ``GATE_SIGMAS``. Only the points ``wanted``
    (all when None) are pooled, into ``start`` (est, variance, used) when given; the others keep their own offset
    or what ``start`` holds."""
    from scipy.spatial import cKDTree

    cat = {name: np.concatenate([getattr(a, name) for a in found]) for name in ("anchor", "normal", "offset",
                                                                               "variance", "ok", "largest")}
    rows = np.flatnonzero(cat["ok"])
    radius = params.radius if params.radius is not None else np.sqrt(REGION_99 * cat["largest"])
    radius = np.ascontiguousarray(np.broadcast_to(radius, cat["ok"].shape)[rows], dtype=np.float64)
    if start is None:
        est, est_var, used = cat["offset"].copy(), cat["variance"].copy(), np.ones(len(cat["offset"]), np.int64)
    else:
        est, est_var, used = start
    queries = np.arange(len(rows)) if wanted is None else np.flatnonzero(wanted[rows])
    if not len(queries):
        return est, est_var, used
    source = np.concatenate([np.full(len(a.ok), k, dtype=np.int64) for k, a in enumerate(found)])
    gating = ((source, -1.0, np.zeros(0), np.zeros(0)) if earlier is None
              else (source, GATE_SIGMAS, earlier[0].copy(), earlier[1].copy()))
    tree = cKDTree(cat["anchor"][rows])
    for first in range(0, len(queries), CHUNK):
        chunk = queries[first:first + CHUNK]
        dist, nb = tree.query(tree.data[chunk], k=min(params.neighbours, len(rows)),
                              distance_upper_bound=float(radius[chunk].max()), workers=-1)
        pool_rows(chunk, nb.reshape(len(chunk), -1), dist.reshape(len(chunk), -1), radius, rows, cat["anchor"],
                  cat["normal"], cat["offset"], cat["variance"], params.gamma, COS_CONE, CENTRE, TRIM_SIGMAS,
                  gating, est, est_var, used)
    return est, est_var, used


def _targets(found: list[Anchors], est: np.ndarray) -> list[np.ndarray]:
    """Per dataset, where each point's line meets the surface its first-pass neighbours put there: the offset's
    change over the cosine, a distance back along the line."""
    at, targets = 0, []
    for a in found:
        sl = slice(at, at + len(a.ok))
        at += len(a.ok)
        cos = _safe_cos(np.einsum("ij,ij->i", a.normal, a.axis))
        targets.append(np.where(a.ok, (a.offset - est[sl]) / cos, 0.0))
    return targets


def _may_join(lines: list[Lines], second: list[Anchors], wanted: np.ndarray, params: PoolingParams) -> np.ndarray:
    """Per point of all datasets, whether the second pass of a ``wanted`` point may pool it: one of its line's
    crossings (any of which may become its second anchor) lies within the pooling radius of a wanted point's second
    anchor. Only those need a first pass of their own."""
    from scipy.spatial import cKDTree

    anchor = np.concatenate([a.anchor for a in second])
    ok = np.concatenate([a.ok for a in second]) & wanted
    out = np.zeros(len(wanted), dtype=bool)
    if not ok.any():
        return out
    largest = np.concatenate([li.largest for li in lines])[ok]
    radius = params.radius if params.radius is not None else float(np.sqrt(REGION_99 * largest.max()))
    tree = cKDTree(anchor[ok])
    at = 0
    for li in lines:
        where, owner = li.crossings()
        dist, _ = tree.query(where, k=1, distance_upper_bound=radius, workers=-1)
        out[at + owner[np.isfinite(dist)]] = True
        at += len(li.pos)
    return out


def _two_passes(lines: list[Lines], params: PoolingParams, wanted: np.ndarray | None
                ) -> tuple[list[Anchors], np.ndarray, np.ndarray, np.ndarray]:
    """The second pass's anchors and the pooled offsets, variances and neighbours of the ``wanted`` points (all when
    None). A tile wants its core's: the first pass runs for them and for the points their second pass may pool, the
    second for them only, with the results a whole epoch gives them."""
    found = [surface_anchors(li) for li in lines]
    est, est_var, used = _pool(found, params, wanted=wanted)
    if wanted is not None:
        second = [surface_anchors(li, tg) for li, tg in zip(lines, _targets(found, est), strict=True)]
        others = _may_join(lines, second, wanted, params) & ~wanted
        est, est_var, used = _pool(found, params, wanted=others, start=(est, est_var, used))
    # the second pass anchors each point on the crossing nearest to its first expectation: where two surfaces lie
    # within the noise along a beam, one point cannot tell which it is on, its neighbourhood can
    found = [surface_anchors(li, tg) for li, tg in zip(lines, _targets(found, est), strict=True)]
    est, est_var, used = _pool(found, params, (est, est_var), wanted=wanted)
    return found, est, est_var, used


def pooled_expectations(datasets: list[Dataset], stations: list[np.ndarray | None], scene: object, origin: np.ndarray,
                        normals: list[np.ndarray], params: PoolingParams, kept: list[np.ndarray] | None = None
                        ) -> tuple[list[Expectation], list[np.ndarray]]:
    """The expectation of every point of ``datasets`` (point clouds with Gaussian covariances), pooled over all of
    them, and per dataset how far from each point its pooling could reach (for a tile's halo). With ``kept`` (per
    dataset, the points whose results are kept) the others keep their own position and covariance."""
    covs = [np.asarray(ds.uncertainty.covariance(ds.n_elements), dtype=np.float64) for ds in datasets]
    lines = [cast_lines(scene, origin, normals, ds.points, c, st, params.reach_sigmas)
             for ds, c, st in zip(datasets, covs, stations, strict=True)]
    wanted = None if kept is None else np.concatenate(kept)
    found, est, est_var, used = _two_passes(lines, params, wanted)
    sizes = np.array([ds.n_elements for ds in datasets])
    largest = max((float(a.largest.max(initial=0.0)) for a in found), default=0.0)
    slack = params.reach_sigmas * np.sqrt(largest)
    widest = params.radius if params.radius is not None else np.sqrt(REGION_99 * largest)
    out, reaches, at = [], [], 0
    for ds, c, a, n in zip(datasets, covs, found, sizes, strict=True):
        sl = slice(at, at + n)
        at += n
        pooled = a.ok & (used[sl] >= MIN_NEIGHBOURS) & (True if wanted is None else wanted[sl])
        # the expectation stays on the point's line (its beam): where the line meets the surface its neighbours
        # put there. Across the line the point's own σ (small for a scanner); along it the pooled σ over the
        # cosine, so its spread along the surface shrinks with the pooling too
        cos = _safe_cos(np.einsum("ij,ij->i", a.normal, a.axis))
        along = np.where(pooled, (a.offset - est[sl]) / cos, 0.0)
        position = ds.points - along[:, None] * a.axis
        aa = np.einsum("ni,nj->nij", a.axis, a.axis)
        across = np.eye(3)[None] - aa
        on_line = across @ c @ across + (est_var[sl] / cos**2)[:, None, None] * aa
        # along the normal only the pooled variance: a line moved sideways meets the surface elsewhere, at the
        # same offset
        nn = np.einsum("ni,nj->nij", a.normal, a.normal)
        tangent = np.eye(3)[None] - nn
        cov_pooled = tangent @ on_line @ tangent + est_var[sl, None, None] * nn
        cov_pooled = 0.5 * (cov_pooled + np.swapaxes(cov_pooled, 1, 2))
        covariance = np.where(pooled[:, None, None], cov_pooled, c)
        out.append(Expectation(position, covariance, np.where(pooled, used[sl], 1)))
        # a neighbour's anchor lies within ``radius`` of this one's, each point within ``slack`` of its anchor, and
        # the second pass's neighbours were anchored by their own first-pass neighbours
        reaches.append(np.where(a.ok, 2 * widest + 3 * slack + np.linalg.norm(ds.points - a.anchor, axis=1), 0.0))
    return out, reaches


def expectations(ctx: StageContext, meshes: Any) -> dict[str, Expectation]:
    """Per recent point dataset with Gaussian covariances, its points' neighbourhood expectations against the
    twin's meshes (``meshes``: the stage's ReferenceMeshes); reported per dataset, and as neighbourhoods in tiles."""
    p = ctx.params
    chosen = [ds for ds in ctx["recent"] if ds.faces is None and isinstance(ds.uncertainty, GaussianUncertainty)]
    skipped = sorted(ds.name for ds in ctx["recent"] if ds not in chosen)
    if meshes is None or meshes.empty or not chosen:
        why = ("the twin holds no visible mesh to anchor expectations on" if chosen
               else "no recent point cloud with Gaussian covariances")
        if p.expectation == "neighbourhood":  # asked for by name; auto pools where it can, quietly
            ctx.log.warning("neighbourhood expectation: %s; every point is judged by itself", why)
        ctx.report(expectation={"pooled_share": 0.0, "why": why})
        return {}
    radius = None if p.pooling_radius is None else p.pooling_radius / UNITS[ctx.epoch.units]
    normals = [ctx["reference"].items[i].dataset.facet_normals(unit=True)[vis] for i, vis in meshes.items]
    stations = [ds.viewpoints[0] if ds.viewpoints is not None and len(ds.viewpoints) == 1 else None
                for ds in chosen]
    kept = [k for ds in chosen if (k := ctx.kept(ds.points)) is not None] or None  # None: a whole epoch's
    found, reaches = pooled_expectations(chosen, stations, meshes.scene, meshes.origin, normals,
                                         PoolingParams(p.pooling_neighbours, radius, p.pooling_gamma,
                                                       p.search_sigmas), kept)
    for ds, reach in zip(chosen, reaches, strict=True):
        ctx.neighbourhoods(ds.points, reach)
    # in a tile, of the points it keeps (the others were not pooled)
    pooled = np.concatenate([e.pooled for e in found] if kept is None else
                            [e.pooled[k] for e, k in zip(found, kept, strict=True)])
    ctx.report(expectation={
        "pooled_share": round(float(np.mean(pooled > 1)), 4) if len(pooled) else 0.0,
        "median_neighbours": int(np.median(pooled[pooled > 1])) if np.any(pooled > 1) else 1,
        "neighbours_quartiles": [int(q) for q in np.percentile(pooled, [25, 50, 75])] if len(pooled) else [],
        "per_point": skipped})
    return {ds.name: e for ds, e in zip(chosen, found, strict=True)}
