"""What both region-of-view stages do inside their volume: which reference elements the recent data matches
(confirms present), and which a sensor could have seen (not occluded)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import raycasting_scene
from ..plugins import StageContext
from ..types import Composite, CompositeItem, Dataset, ItemView, RegionOfView
from .depth import Station
from .depth_view import look_depth
from .occlusion import Sight, confirmed_facets, plane_view, station_view
from .params import SightParams

SPACING_SAMPLE = 20_000  # points whose nearest neighbour the spacing is the median of
SPACING_CHUNK = 2_000_000  # rows of the points one search tree holds at a time


def point_spacing(points: np.ndarray | Sequence[np.ndarray]) -> float:
    """The median nearest-neighbour distance of ``points`` (estimated on at most about 20000 of them); several
    arrays count as their rows stacked, without stacking them."""
    parts = [points] if isinstance(points, np.ndarray) else list(points)
    n = sum(len(p) for p in parts)
    if n < 2:
        return 0.0
    rows = np.arange(0, n, max(1, n // SPACING_SAMPLE))
    return float(np.median(_nearest_other(parts, rows)))


def _nearest_other(parts: list[np.ndarray], rows: np.ndarray) -> np.ndarray:
    """The distance from each of the stacked rows ``rows`` to its nearest other row. Trees of a chunk at a time,
    the nearest taken over the chunks: a tree over the whole epoch held 32 B a point (and the stacked copy 24 B) for
    a 20000-point sample; the distances are the same, computed the same way."""
    starts = np.cumsum([0] + [len(p) for p in parts])
    owner = np.searchsorted(starts, rows, side="right") - 1
    sample = np.empty((len(rows), 3))
    for k, p in enumerate(parts):
        mine = owner == k
        sample[mine] = p[rows[mine] - starts[k]]
    best = np.full(len(rows), np.inf)
    for k, p in enumerate(parts):
        for c0 in range(0, len(p), SPACING_CHUNK):
            chunk = np.asarray(p[c0:c0 + SPACING_CHUNK], dtype=np.float64)
            d, j = cKDTree(chunk).query(sample, k=2, workers=-1)
            d[j + starts[k] + c0 == rows[:, None]] = np.inf  # a row is not its own neighbour
            np.minimum(best, d.min(axis=1), out=best)
    return best


def surface(ds: Dataset, spacing: float) -> tuple[np.ndarray, np.ndarray, str]:
    """The recent data as triangles: meshes as they are; point sets by ball pivoting (measured side only)."""
    import open3d as o3d

    if ds.kind == "mesh":
        return np.asarray(ds.points), np.asarray(ds.faces), "mesh as read"
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(ds.points, dtype=np.float64)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=16))
    if ds.viewpoints is not None:
        pcd.orient_normals_towards_camera_location(np.asarray(ds.viewpoints[0], dtype=np.float64))
    radii = o3d.utility.DoubleVector([1.5 * spacing, 3.0 * spacing, 6.0 * spacing])
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(pcd, radii)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles), \
        f"ball pivoting, radii {[round(r, 6) for r in radii]}"


def _viewpoints(p: SightParams, recent: list[Dataset]) -> np.ndarray | None:
    """The sensor positions: the parameters', else those the recent data carries (None when neither has any)."""
    vps = np.asarray(p.viewpoints, dtype=np.float64) if p.viewpoints else (
        np.vstack([np.atleast_2d(ds.viewpoints) for ds in recent if ds.viewpoints is not None])
        if any(ds.viewpoints is not None for ds in recent) else None)
    if p.occlusion and vps is None:
        raise ValueError("occlusion needs sensor positions: the inputs carry no viewpoints; state them under "
                         "'viewpoints' or set occlusion: false")
    return vps


def _stations(p: SightParams, rov: RegionOfView, vps: np.ndarray | None, stations: list[Station] | None
              ) -> list[Station] | None:
    """The stations sight runs to under ``sight: stations`` (default: every sensor position, with the whole
    volume as its own); None under ``sight: plane``."""
    if p.sight != "stations":
        return stations
    stations = stations if stations is not None else [Station(eye, rov.contains, ()) for eye in (
        vps if vps is not None else np.zeros((0, 3)))]
    if not stations:
        raise ValueError("sight: stations needs sensor positions: the inputs carry no viewpoints; state them "
                         "under 'viewpoints'")
    return stations


def _recent_surfaces(p: SightParams, recent: list[Dataset], spacing: float) -> tuple[Any, list[str]]:
    """The recent data as one ray-casting scene of triangles (None without occlusion or triangles), and how each
    dataset became triangles."""
    surfaces, how = [], []
    if p.occlusion:
        for ds in recent:
            v, f, method = surface(ds, spacing)
            surfaces.append((v, f))
            how.append(f"{ds.name}: {method} ({len(f)} triangles)")
    scene = raycasting_scene(surfaces) if p.occlusion and any(len(f) for _, f in surfaces) else None
    return scene, how


def _match_radii(recent: list[Dataset], n_points: int, match: float) -> tuple[np.ndarray, np.ndarray]:
    """Per recent element, the radius within which it matches a reference element, and its largest-axis σ: a noisy
    recent element still matches an element it measured, so the radius grows to 3σ of its largest axis."""
    sig = np.concatenate([np.sqrt(np.linalg.eigvalsh(ds.element_covariance())[:, -1]) if ds.uncertainty is not None
                          else np.zeros(ds.n_elements) for ds in recent]) if recent else np.zeros(0)
    radius = np.maximum(match, 3.0 * np.broadcast_to(sig, (n_points,))) if n_points else np.zeros(0)
    return radius, np.broadcast_to(sig, (n_points,))


def _matched(item: CompositeItem, pos: np.ndarray, inside: np.ndarray, normal: np.ndarray | None, tree: cKDTree,
             rpts: np.ndarray, radius: np.ndarray, sig: np.ndarray) -> np.ndarray:
    """Which elements of a reference item inside the volume recent data lies close to (and, on a facet, in its
    plane): the elements the recent data confirms present."""
    # and a noisy reference element (an earlier ToF scan) is matched within 3σ of its own largest axis
    own = np.zeros(int(inside.sum()))
    if item.dataset.uncertainty is not None:
        own = 3.0 * np.sqrt(np.linalg.eigvalsh(item.dataset.element_covariance()[inside])[:, -1])
    reach = float(max(radius.max(), own.max(initial=0.0)))
    d, j = tree.query(pos[inside], k=32, distance_upper_bound=reach, workers=-1)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    hit = ok & (d <= np.maximum(radius[jj], own[:, None]))
    if normal is not None:
        # on a facet, recent data must also lie in its plane within the uncertainties (3σ of either side): a surface
        # 5 mm behind a removed bracket's plate is not the plate
        unit = normal[inside] / np.maximum(np.linalg.norm(normal[inside], axis=1, keepdims=True), 1e-300)
        off = np.abs(np.einsum("ij,ikj->ik", unit, rpts[jj] - pos[inside][:, None, :]))
        hit &= off <= np.maximum(3.0 * sig[jj], own[:, None])
    near = np.zeros(len(pos), dtype=bool)
    near[np.flatnonzero(inside)] = np.any(hit, axis=1)
    return near


@dataclass(frozen=True)
class ItemLook:
    """One reference item as the volume holds it: its element positions, which lie inside the volume, its facet
    normals (None for points) and which elements the recent data matches (confirms present)."""

    item: CompositeItem
    pos: np.ndarray
    inside: np.ndarray
    normal: np.ndarray | None
    near: np.ndarray


def _confirm(reference: Composite, rov: RegionOfView, rpts: np.ndarray, recent: list[Dataset], match: float
             ) -> list[ItemLook]:
    """Per reference item: its element positions, which lie inside the volume, its facet normals and which
    elements the recent data matches (confirms present)."""
    tree = cKDTree(rpts) if len(rpts) else None
    radius, sig = _match_radii(recent, len(rpts), match)
    looked = []
    for item in reference.items:
        pos = item.dataset.element_positions()
        inside = rov.contains(pos) & item.visible
        normal = item.dataset.facet_normals() if item.dataset.faces is not None else None
        near = np.zeros(len(pos), dtype=bool)
        if tree is not None and inside.any():
            near = _matched(item, pos, inside, normal, tree, rpts, radius, sig)
        looked.append(ItemLook(item, pos, inside, normal, near))
    return looked


def look(ctx: StageContext, rov: RegionOfView, parts: list[str], stations: list[Station] | None = None
         ) -> dict[str, Any]:
    """In view and matched, per reference item, and the report of how."""
    p = ctx.params
    recent: list[Dataset] = ctx["recent"]
    reference: Composite = ctx.get("reference") or Composite()
    positions = [ds.element_positions() for ds in recent]
    spacing = point_spacing(positions)
    if p.sight == "depth":
        del positions  # a mesh's centroids are not held while the depth images are
        return look_depth(ctx, rov, parts, stations, spacing)
    rpts = positions[0] if len(positions) == 1 else np.vstack(positions) if positions else np.zeros((0, 3))
    offset = p.offset or 3 * spacing
    match = p.match_distance or 3 * spacing
    vps = _viewpoints(p, recent)
    stations = _stations(p, rov, vps, stations)
    scene, how = _recent_surfaces(p, recent, spacing)
    # measured points in the line of sight hide an element even where the intermediate surface has holes (thin
    # parts seen at grazing angles): recent point clouds only, meshes are their own surface
    cloud = [ds.points for ds in recent if ds.kind == "points"]
    point_tree = cKDTree(np.vstack(cloud)) if p.occlusion and cloud else None
    looked = _confirm(reference, rov, rpts, recent, match)
    # reference facets the recent data confirms hide what lies behind them, seen from their front: the measured
    # surface of a thin part at grazing angles has holes where the CAD facet it confirms has none
    confirmed = confirmed_facets([(lk.item.dataset, lk.near) for lk in looked if lk.normal is not None]) \
        if p.occlusion and p.confirmed_occlude else None
    sight = Sight(scene, point_tree, confirmed, offset, spacing, p.rule)
    views, counts = {}, {"inside": 0, "occluded": 0, "in_view": 0, "unmatched_in_view": 0}
    for lk in looked:
        inside = lk.inside
        if p.sight == "stations":
            view = station_view(lk.pos, inside, lk.normal, stations, sight, p)
            counts["occluded"] += int((inside & ~view).sum())
        else:
            view, inside, n_hidden = plane_view(lk.pos, inside, lk.normal, vps, sight, p)
            counts["occluded"] += n_hidden
        near = lk.near
        views[lk.item.key] = ItemView(view, near & view)
        counts["inside"] += int(inside.sum())
        counts["in_view"] += int(view.sum())
        counts["unmatched_in_view"] += int((view & ~near).sum())
    ctx.report(region_of_view={"parts": parts, "surfaces": how, "spacing": spacing, "offset": offset,
                               "match_distance": match, "rule": p.rule, **counts})
    ctx.log.info("region of view: %d reference elements inside, %d occluded, %d in view of which %d unmatched",
                 counts["inside"], counts["occluded"], counts["in_view"], counts["unmatched_in_view"])
    return {"rov": RegionOfView(rov.vertices, rov.faces, rov.parts, views=views, method="; ".join(parts))}
