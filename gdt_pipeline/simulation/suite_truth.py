"""Ground truth of a suite scene by area: samples spread over every facet (at least one per ~(5 mm)², up to a cap),
which of them a station could see (inside its pinhole frustum and range, facing it, not hidden by the as-is scene),
which lie where the as-is scene no longer has a surface (vacated), and per facet of a reconstructed mesh scan the
share of its area on changed geometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry import distance_to, raycasting_scene, triangle_areas, triangle_points
from .paper_scene import TOLERANCE
from .scanner import ScannerSpec

SAMPLE_SPACING = 0.005  # m: at least one sample per (5 mm)² of facet area ...
MAX_SAMPLES_PER_FACET = 2000  # ... up to this many (a 2 m² floor triangle gets one per ~(3 cm)²)
FACING_COS = 0.05  # a facet seen at more than ~87° from its normal is not seen
TRIM_SPACINGS = 1.0  # a mesh scan keeps the facets whose corners lie within this many point spacings of its points
DEGENERATE_AREA = 1e-12  # the mesh reader's rule: doubled area ≤ this × the longest squared edge is no facet
SCAN_FACET_SAMPLES = np.array([[1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6],
                               [1 / 6, 1 / 6, 2 / 3]])  # barycentric: the centroid and one point towards each corner


def area_samples(mesh, rng: np.random.Generator, spacing: float = SAMPLE_SPACING,
                 cap: int = MAX_SAMPLES_PER_FACET) -> tuple[np.ndarray, np.ndarray]:
    """Uniform random samples over each facet, ``ceil(area / spacing²)`` of them (1 … ``cap``): (points, facet)."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    count = np.clip(np.ceil(area / spacing**2), 1, cap).astype(np.int64)
    facet = np.repeat(np.arange(len(tri)), count)
    u, v = rng.random((2, len(facet)))
    return triangle_points(tri, facet, u, v), facet


def in_frustum(points: np.ndarray, eye: np.ndarray, target: np.ndarray, spec: ScannerSpec) -> np.ndarray:
    """Whether each point is inside the pinhole frustum of a simulated station (its rays' image, up = +z)."""
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    d = points - eye
    z = d @ fwd
    tan_h = np.tan(np.radians(spec.fov_deg) / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (z > 0) & (np.abs(d @ right) <= tan_h * z) & (np.abs(d @ up) <= tan_h / spec.aspect * z)


def seen_from(points: np.ndarray, normals: np.ndarray, stations: list[tuple[np.ndarray, np.ndarray, ScannerSpec]],
              blockers: list) -> np.ndarray:
    """Whether any station sees each point: in its frustum and range, facing it, and the first surface of
    ``blockers`` along the ray not clearly in front of it (TOLERANCE)."""
    import open3d as o3d

    scene = raycasting_scene(blockers)
    seen = np.zeros(len(points), dtype=bool)
    for eye, target, spec in stations:
        d = points - eye
        dist = np.linalg.norm(d, axis=1)
        d = d / dist[:, None]
        cand = in_frustum(points, eye, target, spec) & (dist <= spec.max_range)
        cand &= np.einsum("ij,ij->i", normals, -d) > FACING_COS
        cand &= ~seen
        idx = np.flatnonzero(cand)
        if not idx.size:
            continue
        rays = np.hstack([np.broadcast_to(eye, (idx.size, 3)), d[idx]]).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        seen[idx] = ~(t < dist[idx] - TOLERANCE)
    return seen


def cad_facet_truth(mesh, state: str, stations: list, asis: list, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Per facet of one CAD part: area, visible fraction, vacated fraction (off the as-is surfaces by more than
    TOLERANCE), visible-and-vacated fraction, and whether it counts as removed (part removed, or moved and most of
    the facet vacated)."""
    pts, facet = area_samples(mesh, rng)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)[facet]
    seen = seen_from(pts, normals, stations, asis)
    vacated = np.ones(len(pts), bool) if state == "removed" else distance_to(asis, pts) > TOLERANCE
    count = np.bincount(facet, minlength=len(mesh.faces)).astype(np.float64)

    def share(flag: np.ndarray) -> np.ndarray:
        return np.bincount(facet, weights=flag.astype(np.float64), minlength=len(mesh.faces)) / count

    visible, vac, vis_vac = share(seen), share(vacated), share(seen & vacated)
    if state == "removed":
        removed = np.ones(len(mesh.faces), bool)
    elif state == "moved":
        removed = vac >= 0.5
    else:
        removed = np.zeros(len(mesh.faces), bool)
    return {"area": np.asarray(mesh.area_faces, dtype=np.float64), "visible": visible, "vacated": vac,
            "visible_removed": vis_vac if state in ("removed", "moved") else np.zeros(len(vac)),
            "removed": removed, "in_view": visible >= 0.5}


def point_changed(clean: np.ndarray, cad: list) -> np.ndarray:
    """Whether each noise-free scan point lies off the CAD surfaces by more than TOLERANCE."""
    return distance_to(cad, clean) > TOLERANCE


def clean_mesh_scan(path: Path, points: np.ndarray) -> None:
    """Drop the facets the mesh reader would drop (repeated corners, no area) and those Poisson invented away from
    the data (a corner farther than TRIM_SPACINGS median point spacings from every scan point), and rewrite the PLY:
    a scanner's software meshes where it measured, and the twin's facets are then the file's, one to one with the
    per-facet truth."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    mesh = o3d.io.read_triangle_mesh(str(path))
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    doubled = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    longest = np.max([((b - a) ** 2).sum(1), ((c - b) ** 2).sum(1), ((a - c) ** 2).sum(1)], axis=0)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    tree = cKDTree(points)
    spacing = float(np.median(tree.query(points, k=2)[0][:, 1]))
    # the membranes Poisson stretches over occlusion shadows start at the data's edge: a looser bound (3 spacings,
    # or a local spacing) kept 2-7 mm-off strips along every shadow, 15-30 % of a scan's area in a scene of 1 m
    far = tree.query(v)[0][f].max(axis=1) > TRIM_SPACINGS * spacing
    bad = repeated | (doubled <= DEGENERATE_AREA * longest) | far
    if bad.any():
        mesh.remove_triangles_by_mask(bad)
        mesh.remove_unreferenced_vertices()
        o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=False)


def mesh_facet_truth(path: Path, asis: list, cad: list) -> dict[str, np.ndarray]:
    """Per facet of a reconstructed mesh scan: its area, the share of its area on changed geometry (four samples,
    each taken to the nearest true as-is surface, changed when that lies off the CAD by more than TOLERANCE) and
    the mean distance of the samples to the true surfaces (large on surface Poisson invented)."""
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    v, f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles)
    tri = v[f]
    area = triangle_areas(tri)
    samples = np.einsum("sk,fkj->fsj", SCAN_FACET_SAMPLES, tri).reshape(-1, 3)
    ans = raycasting_scene(asis).compute_closest_points(o3d.core.Tensor(samples.astype(np.float32)))
    closest = ans["points"].numpy().astype(np.float64)
    offset = np.linalg.norm(samples - closest, axis=1).reshape(len(f), -1).mean(axis=1)
    changed = point_changed(closest, cad).reshape(len(f), -1).mean(axis=1)
    return {"facet_changed": changed, "facet_area": area, "facet_offset": offset}
