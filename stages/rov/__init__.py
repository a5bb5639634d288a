"""Region of View (paper Sec. 4.1): what the sensors of an epoch saw, so that reference geometry the recent data
does not show is called "removed" only where a sensor could have seen it.

- ``sensor_frustum``: the bounding volume is the union of the sensors' frusta: per recent dataset with viewpoints,
  a pinhole frustum from the scanner's pose file beside the input (``<scan>_pose.json``, as the simulator writes:
  viewpoint, target, field of view, aspect, range), else the tightest pinhole frustum around the directions to the
  dataset's own points (plus a margin); near and far from the parameters or the data.
- ``manual_box``: a user-given axis-aligned box, as the paper did for its experiments.

Both then remove occlusion with the Plane of Sight (POS): a polygon through the sensor positions (a point for one
sensor, a segment for two); for each reference element inside the volume a ray runs from it to the closest point of
the POS; where it crosses the recent data an odd number of times (Open3D ``list_intersections`` on the segment), the
element is not in view (the paper's rule). Point-cloud recent data first gets an intermediate surface (Open3D ball
pivoting: it keeps only the measured side, which the parity rule needs), stated in the report. An element in view is
"matched" when recent data lies within ``match_distance`` of it; the fusion marks in-view, unmatched elements
removed and the others outside the region of view.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat
from scipy.spatial import ConvexHull, cKDTree

from gdt_pipeline import Composite, Dataset, RegionOfView, StageContext, StageSpec, hookimpl
from gdt_pipeline.geometry import raycasting_scene


class OcclusionParams(BaseModel):
    """What both region-of-view stages share: occlusion by the Plane of Sight and matching."""

    model_config = ConfigDict(extra="forbid")
    occlusion: bool = Field(True, description="Remove elements hidden behind recent data (Plane of Sight).")
    rule: Literal["odd", "any"] = Field("odd", description="Occluded when the sight ray crosses the recent data an "
                                                           "odd number of times (the paper), or at all.")
    offset: PositiveFloat | None = Field(None, description="The sight ray starts this far towards the POS, so the "
                                                           "element's own measured surface is not counted (default: "
                                                           "3 × the recent data's point spacing).")
    match_distance: PositiveFloat | None = Field(None, description="Recent data within this distance of an element "
                                                                   "matches it (default: 3 × the point spacing; "
                                                                   "at least 3σ of the recent element).")
    cull_back_faces: bool = Field(True, description="Reference facets facing away from every sensor are not in "
                                                    "view (needs outward facet normals, as CAD solids have).")
    viewpoints: list[list[float]] | None = Field(None, description="Sensor positions for the POS (default: those "
                                                                   "the inputs carry).")
    confirmed_occlude: bool = Field(True, description="Reference facets the recent data matches (confirmed present) "
                                                      "hide what lies behind them too, seen from their front.")
    sight: Literal["plane", "stations"] = Field(
        "plane", description="plane: the sight ray runs to the Plane of Sight through all sensor positions (the "
                             "paper; for sensors along one sweep); stations: to each sensor whose own frustum holds "
                             "the element and which the facet faces, in view when any such ray is clear (for "
                             "stations all around the object, where one plane through them cuts through it).")


class FrustumParams(OcclusionParams):
    """The union of the sensors' frusta."""

    fov_deg: float | None = Field(None, gt=0, lt=180, description="Horizontal field of view when no pose file says "
                                                                  "(default: fitted to the data).")
    aspect: PositiveFloat | None = Field(None, description="Width / height of the image when no pose file says.")
    near: float = Field(0.05, ge=0, description="Nearest range measured (twin units).")
    far: PositiveFloat | None = Field(None, description="Farthest range (default: the pose file's, else 1.05 × the "
                                                        "farthest point).")
    margin_deg: float = Field(1.0, ge=0, description="Angular margin around a frustum fitted to the data.")


class BoxParams(OcclusionParams):
    """A user-given box."""

    lower: list[float] = Field(min_length=3, max_length=3, description="Lower corner (twin units).")
    upper: list[float] = Field(min_length=3, max_length=3, description="Upper corner (twin units).")


def _frame(fwd: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    fwd = fwd / np.linalg.norm(fwd)
    helper = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.95 else np.array([1.0, 0.0, 0.0])
    right = np.cross(fwd, helper)
    right /= np.linalg.norm(right)
    return fwd, right, np.cross(right, fwd)


def _frustum_mesh(eye: np.ndarray, fwd: np.ndarray, u: tuple[float, float], v: tuple[float, float], near: float,
                  far: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed pinhole frustum: image-plane tangent bounds u (right) and v (up), between near and far depth."""
    f, r, up = _frame(fwd)
    corners = []
    for depth in (near, far):
        for a, b in ((u[0], v[0]), (u[1], v[0]), (u[1], v[1]), (u[0], v[1])):
            corners.append(eye + depth * (f + a * r + b * up))
    verts = np.array(corners)
    faces = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                      [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    return verts, faces


def _pose(ds: Dataset, workflow_dir: Path) -> dict[str, Any] | None:
    if ds.source is None:
        return None
    path = Path(ds.source.path)
    path = path if path.is_absolute() else workflow_dir / path
    pose = path.with_name(path.stem + "_pose.json")
    if not pose.is_file():
        return None
    try:
        data = json.loads(pose.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{pose}: not a readable pose file: {exc}") from exc
    return data if data.get("target") is not None and data.get("scanner") else None


def _dataset_frusta(ds: Dataset, p: FrustumParams, workflow_dir: Path
                    ) -> list[tuple[np.ndarray, np.ndarray, str, np.ndarray]]:
    pose = _pose(ds, workflow_dir)
    pts = ds.element_positions()
    if pose is not None and (pose["scanner"].get("kind", "pinhole") == "pinhole"):
        eye, target = np.asarray(pose["viewpoint"], float), np.asarray(pose["target"], float)
        sc = pose["scanner"]
        th = np.tan(np.radians(p.fov_deg or sc["fov_deg"]) / 2)
        tv = th / (p.aspect or sc["aspect"])
        far = p.far or float(sc["max_range"])
        verts, faces = _frustum_mesh(eye, target - eye, (-th, th), (-tv, tv), p.near, far)
        return [(verts, faces, f"{ds.name}: pinhole frustum from its pose file", eye)]
    if ds.viewpoints is None or not len(pts):
        return []
    out = []
    for eye in np.atleast_2d(ds.viewpoints):
        d = pts - eye
        fwd = d.mean(axis=0)
        f, r, up = _frame(fwd)
        depth = d @ f
        if np.any(depth <= 1e-9 * np.linalg.norm(d, axis=1)):
            raise ValueError(f"dataset {ds.name!r}: its points surround viewpoint {eye.tolist()} (a spherical scan); "
                             f"state the region with manual_box")
        a, b = (d @ r) / depth, (d @ up) / depth
        m = np.tan(np.radians(p.margin_deg))
        far = p.far or 1.05 * float(np.linalg.norm(d, axis=1).max())
        verts, faces = _frustum_mesh(eye, f, (a.min() - m, a.max() + m), (b.min() - m, b.max() + m), p.near, far)
        out.append((verts, faces, f"{ds.name}: frustum fitted to its points from {np.round(eye, 4).tolist()}", eye))
    return out


def _spacing(points: np.ndarray) -> float:
    if len(points) < 2:
        return 0.0
    sample = points[:: max(1, len(points) // 20000)]
    d, _ = cKDTree(points).query(sample, k=2)
    return float(np.median(d[:, 1]))


def _surface(ds: Dataset, spacing: float) -> tuple[np.ndarray, np.ndarray, str]:
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


def _pos_closest(points: np.ndarray, viewpoints: np.ndarray) -> np.ndarray:
    """The closest point of the Plane of Sight (the polygon through the viewpoints) to each point."""
    vp = np.atleast_2d(viewpoints)
    if len(vp) == 1:
        return np.broadcast_to(vp[0], points.shape).copy()
    centre = vp.mean(axis=0)
    _, s, vt = np.linalg.svd(vp - centre)
    if len(vp) == 2 or s[1] < 1e-9 * max(s[0], 1e-12):  # collinear: the POS is a segment
        a, b = vp[np.argmin((vp - centre) @ vt[0])], vp[np.argmax((vp - centre) @ vt[0])]
        t = np.clip(((points - a) @ (b - a)) / max(float((b - a) @ (b - a)), 1e-30), 0, 1)
        return a + t[:, None] * (b - a)
    e1, e2 = vt[0], vt[1]
    uv = np.column_stack([(vp - centre) @ e1, (vp - centre) @ e2])
    hull = uv[ConvexHull(uv).vertices]
    q = np.column_stack([(points - centre) @ e1, (points - centre) @ e2])
    # inside the polygon: the projection; outside: the closest point on its boundary edges
    best = q.copy()
    inside = np.ones(len(q), dtype=bool)
    best_d = np.full(len(q), np.inf)
    edge_pt = np.zeros_like(q)
    for i in range(len(hull)):  # a loop over the few polygon edges; the points are vectorised
        a, b = hull[i], hull[(i + 1) % len(hull)]
        ab = b - a
        inside &= (ab[0] * (q[:, 1] - a[1]) - ab[1] * (q[:, 0] - a[0])) >= 0
        t = np.clip(((q - a) @ ab) / float(ab @ ab), 0, 1)
        c = a + t[:, None] * ab
        d = np.linalg.norm(q - c, axis=1)
        closer = d < best_d
        best_d[closer], edge_pt[closer] = d[closer], c[closer]
    best[~inside] = edge_pt[~inside]
    return centre + best[:, :1] * e1 + best[:, 1:] * e2


def _occluded(origins: np.ndarray, targets: np.ndarray, scene, rule: str) -> np.ndarray:
    """Whether each sight segment crosses the recent surfaces (an odd number of times, or at all)."""
    if not len(origins) or scene is None:
        return np.zeros(len(origins), dtype=bool)
    ray, _ = _segment_hits(scene, origins, targets)
    counts = np.bincount(ray, minlength=len(origins))
    return counts % 2 == 1 if rule == "odd" else counts > 0


def _segment_hits(scene, origins: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every crossing of the scene strictly between each origin and its target: (segment index, triangle id)."""
    import open3d as o3d

    rays = np.hstack([origins, targets - origins]).astype(np.float32)  # direction unnormalised: t in [0, 1] = segment
    ans = scene.list_intersections(o3d.core.Tensor(rays))
    t = ans["t_hit"].numpy()
    ray = np.repeat(np.arange(len(origins)), np.diff(ans["ray_splits"].numpy()))
    on_segment = (t > 0) & (t < 1)
    return ray[on_segment], ans["primitive_ids"].numpy()[on_segment]


def _shadowed(origins: np.ndarray, targets: np.ndarray, tree: cKDTree, radius: float, chunk: int = 2_000_000
              ) -> np.ndarray:
    """Whether a measured point lies within ``radius`` of each sight segment (sampled every radius)."""
    out = np.zeros(len(origins), dtype=bool)
    if not len(origins) or radius <= 0:
        return out
    length = np.linalg.norm(targets - origins, axis=1)
    steps = np.clip(np.ceil(length / radius).astype(np.int64), 1, 4000)
    # stop short of the sensor end: the sensor's own position holds no points, but its neighbourhood may
    ray = np.repeat(np.arange(len(origins)), steps)
    first = np.repeat(np.cumsum(steps) - steps, steps)
    t = (np.arange(len(ray)) - first + 0.5) / steps[ray]
    for s0 in range(0, len(ray), chunk):
        r, tt = ray[s0:s0 + chunk], t[s0:s0 + chunk]
        pts = origins[r] + tt[:, None] * (targets[r] - origins[r])
        d, _ = tree.query(pts, distance_upper_bound=radius)
        np.logical_or.at(out, r[np.isfinite(d)], True)
    return out


Station = tuple[np.ndarray, Any]  # a sensor position and the test of which points its own volume holds


def _look(ctx: StageContext, rov: RegionOfView, parts: list[str], stations: list[Station] | None = None
          ) -> dict[str, Any]:
    """In view and matched, per reference item, and the report of how."""
    p = ctx.params
    recent: list[Dataset] = ctx["recent"]
    reference: Composite = ctx.get("reference") or Composite()
    rpts = np.vstack([ds.element_positions() for ds in recent]) if recent else np.zeros((0, 3))
    spacing = _spacing(rpts)
    offset = p.offset or 3 * spacing
    match = p.match_distance or 3 * spacing
    vps = np.asarray(p.viewpoints, dtype=np.float64) if p.viewpoints else (
        np.vstack([np.atleast_2d(ds.viewpoints) for ds in recent if ds.viewpoints is not None])
        if any(ds.viewpoints is not None for ds in recent) else None)
    if p.occlusion and vps is None:
        raise ValueError("occlusion needs sensor positions: the inputs carry no viewpoints; state them under "
                         "'viewpoints' or set occlusion: false")
    if p.sight == "stations":
        stations = stations if stations is not None else [(eye, rov.contains) for eye in (
            vps if vps is not None else np.zeros((0, 3)))]
        if not stations:
            raise ValueError("sight: stations needs sensor positions: the inputs carry no viewpoints; state them "
                             "under 'viewpoints'")
    surfaces, how = [], []
    if p.occlusion:
        for ds in recent:
            v, f, method = _surface(ds, spacing)
            surfaces.append((v, f))
            how.append(f"{ds.name}: {method} ({len(f)} triangles)")
    sight_scene = raycasting_scene(surfaces) if p.occlusion and any(len(f) for _, f in surfaces) else None
    tree = cKDTree(rpts) if len(rpts) else None
    # measured points in the line of sight hide an element even where the intermediate surface has holes (thin
    # parts seen at grazing angles): recent point clouds only, meshes are their own surface
    cloud = [ds.points for ds in recent if ds.kind == "points"]
    point_tree = cKDTree(np.vstack(cloud)) if p.occlusion and cloud else None
    # a noisy recent element still matches an element it measured: the radius grows to 3σ of its largest axis
    sig = np.concatenate([np.sqrt(np.linalg.eigvalsh(ds.element_covariance())[:, -1]) if ds.uncertainty is not None
                          else np.zeros(ds.n_elements) for ds in recent]) if recent else np.zeros(0)
    radius = np.maximum(match, 3.0 * np.broadcast_to(sig, (len(rpts),))) if len(rpts) else np.zeros(0)
    sig3 = np.broadcast_to(sig, (len(rpts),))
    in_view, matched, counts = {}, {}, {"inside": 0, "occluded": 0, "in_view": 0, "unmatched_in_view": 0}
    # first pass: which reference elements inside the volume the recent data matches (confirms present)
    looked = []
    for item in reference.items:
        pos = item.dataset.element_positions()
        inside = rov.contains(pos) & item.visible
        normal = item.dataset.facet_normals() if item.dataset.faces is not None else None
        near = np.zeros(len(pos), dtype=bool)
        if tree is not None and inside.any():
            # and a noisy reference element (an earlier ToF scan) is matched within 3σ of its own largest axis
            own = np.zeros(int(inside.sum()))
            if item.dataset.uncertainty is not None:
                own = 3.0 * np.sqrt(np.linalg.eigvalsh(item.dataset.element_covariance()[inside])[:, -1])
            reach = float(max(radius.max(), own.max(initial=0.0)))
            d, j = tree.query(pos[inside], k=32, distance_upper_bound=reach)
            ok = np.isfinite(d)
            jj = np.where(ok, j, 0)
            hit = ok & (d <= np.maximum(radius[jj], own[:, None]))
            if normal is not None:
                # on a facet, recent data must also lie in its plane within the uncertainties (3σ of either
                # side): a surface 5 mm behind a removed bracket's plate is not the plate
                unit = normal[inside] / np.maximum(np.linalg.norm(normal[inside], axis=1, keepdims=True), 1e-300)
                off = np.abs(np.einsum("ij,ikj->ik", unit, rpts[jj] - pos[inside][:, None, :]))
                hit &= off <= np.maximum(3.0 * sig3[jj], own[:, None])
            near[np.flatnonzero(inside)] = np.any(hit, axis=1)
        looked.append((item, pos, inside, normal, near))
    # reference facets the recent data confirms hide what lies behind them, seen from their front: the measured
    # surface of a thin part at grazing angles has holes where the CAD facet it confirms has none
    confirmed = _confirmed([(it.dataset, nr) for it, _, _, nr_normal, nr in looked if nr_normal is not None]) \
        if p.occlusion and p.confirmed_occlude else None
    for item, pos, inside, normal, near in looked:
        if p.sight == "stations":
            view = _station_view(pos, inside, normal, stations, sight_scene, point_tree, offset, spacing, p,
                                 confirmed)
            counts["occluded"] += int((inside & ~view).sum())
        else:
            if p.cull_back_faces and normal is not None and vps is not None:
                # a facet facing away from every sensor was not seen, whatever lies between: a solid's far side
                inside = inside & np.any(np.einsum("fj,sfj->sf", normal, vps[:, None, :] - pos[None]) > 0, axis=0)
            view = inside.copy()
            idx = np.flatnonzero(inside)
            if p.occlusion and idx.size:
                pos_target = _pos_closest(pos[idx], vps)
                hidden = _hidden(pos[idx], pos_target, sight_scene, point_tree, offset, spacing, p.rule, confirmed)
                view[idx[hidden]] = False
                counts["occluded"] += int(hidden.sum())
        in_view[item.key], matched[item.key] = view, near & view
        counts["inside"] += int(inside.sum())
        counts["in_view"] += int(view.sum())
        counts["unmatched_in_view"] += int((view & ~near).sum())
    ctx.report(region_of_view={"parts": parts, "surfaces": how, "spacing": spacing, "offset": offset,
                               "match_distance": match, "rule": p.rule, **counts})
    ctx.log.info("region of view: %d reference elements inside, %d occluded, %d in view of which %d unmatched",
                 counts["inside"], counts["occluded"], counts["in_view"], counts["unmatched_in_view"])
    return {"rov": RegionOfView(rov.vertices, rov.faces, rov.parts, in_view=in_view, matched=matched,
                                method="; ".join(parts))}


def _confirmed(items: list[tuple[Dataset, np.ndarray]]):  # -> (RaycastingScene, facet normals) | None
    """The reference facets the recent data matched, as one ray-casting scene (one geometry, so that Open3D's
    primitive ids index the stacked normals) with their normals."""
    tris = [ds.points[ds.faces[near]] for ds, near in items if near.any()]
    if not tris:
        return None
    soup = np.vstack(tris)
    scene = raycasting_scene([(soup.reshape(-1, 3), np.arange(3 * len(soup)).reshape(-1, 3))])
    return scene, np.vstack([ds.facet_normals(near) for ds, near in items if near.any()])


def _blocked_by_confirmed(origins: np.ndarray, targets: np.ndarray, confirmed) -> np.ndarray:
    """Whether each sight segment passes through a confirmed facet from its front (a solid's far faces, seen from
    behind on the way out, do not count: closed CAD solids would otherwise cancel by parity)."""
    if confirmed is None or not len(origins):
        return np.zeros(len(origins), dtype=bool)
    scene, normals = confirmed
    ray, prim = _segment_hits(scene, origins, targets)
    front = np.einsum("ij,ij->i", normals[prim], (targets - origins)[ray]) > 0
    return np.bincount(ray[front], minlength=len(origins)) > 0


def _hidden(pos: np.ndarray, target: np.ndarray, scene, point_tree: cKDTree | None, offset: float, spacing: float,
            rule: str, confirmed=None) -> np.ndarray:
    """Whether recent data, or a reference facet it confirmed, hides each element from its sight target (the sight
    ray starts ``offset`` towards the target, so that the element's own measured surface does not count)."""
    direction = target - pos
    length = np.linalg.norm(direction, axis=1, keepdims=True)
    start = pos + direction / np.maximum(length, 1e-12) * np.minimum(offset, 0.5 * length)
    hidden = _occluded(start, target, scene, rule)
    if point_tree is not None:
        hidden |= _shadowed(start, target, point_tree, 1.5 * spacing)
    # confirmed facets are exact geometry without noise: their rays start just off the element, so that a thin part
    # (a flange thinner than the offset measured surfaces need) still hides the face it covers
    near_start = pos + direction / np.maximum(length, 1e-12) * np.minimum(1e-3 * offset, 0.5 * length)
    return hidden | _blocked_by_confirmed(near_start, target, confirmed)


def _station_view(pos: np.ndarray, inside: np.ndarray, normal: np.ndarray | None, stations: list[Station], scene,
                  point_tree: cKDTree | None, offset: float, spacing: float, p: OcclusionParams, confirmed=None
                  ) -> np.ndarray:
    """In view from at least one station: inside its own volume, facing it, with a clear sight ray to it. Stations
    are tried in turn on the elements none has seen yet (a loop over the few stations; elements are vectorised)."""
    view = np.zeros(len(pos), dtype=bool)
    todo = np.flatnonzero(inside)
    for eye, contains in stations:
        if not todo.size:
            break
        cand = todo[contains(pos[todo])]
        if p.cull_back_faces and normal is not None:
            cand = cand[np.einsum("ij,ij->i", normal[cand], eye[None, :] - pos[cand]) > 0]
        if p.occlusion and cand.size:
            cand = cand[~_hidden(pos[cand], np.broadcast_to(eye, (cand.size, 3)), scene, point_tree, offset, spacing,
                                 p.rule, confirmed)]
        view[cand] = True
        todo = todo[~view[todo]]
    return view


def _sensor_frustum(ctx: StageContext) -> dict[str, Any]:
    frusta = []
    for ds in ctx["recent"]:
        frusta += _dataset_frusta(ds, ctx.params, ctx.epoch.workflow_dir)
    if not frusta:
        raise ValueError("no recent dataset carries viewpoints or a pose file: give the inputs 'viewpoints' or use "
                         "manual_box")
    verts, faces, start = [], [], 0
    for v, f, _, _ in frusta:
        verts.append(v)
        faces.append(f + start)
        start += len(v)
    rov = RegionOfView(np.vstack(verts), np.vstack(faces), tuple(len(f) for _, f, _, _ in frusta))
    stations = [(eye, lambda q, k=k: rov.contains(q, part=k)) for k, (_, _, _, eye) in enumerate(frusta)]
    return _look(ctx, rov, [how for _, _, how, _ in frusta], stations)


def _manual_box(ctx: StageContext) -> dict[str, Any]:
    p = ctx.params
    rov = RegionOfView.box(p.lower, p.upper)
    return _look(ctx, rov, [f"box {p.lower} .. {p.upper}"])


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in region-of-view stages."""
    common = {"family": "rov", "version": "1.1.0", "requires": ("recent",), "optional": ("reference",),
              "provides": ("rov",)}
    return [
        StageSpec(name="sensor_frustum", params=FrustumParams, run=_sensor_frustum,
                  description="Union of the sensors' frusta, minus what recent data occludes (Plane of Sight).",
                  **common),
        StageSpec(name="manual_box", params=BoxParams, run=_manual_box,
                  description="A user-given box, minus what recent data occludes (Plane of Sight).", **common),
    ]
