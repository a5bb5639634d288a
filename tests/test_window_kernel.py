"""The compiled depth-image window test against a plain per-sample reference written from its definition: the same
counts of points in front of, at and behind each sample, and the same pooled sums, for facet and point samples."""

from __future__ import annotations

import numpy as np
import trimesh

from gdt_pipeline import Dataset, GaussianUncertainty
from gdt_pipeline.region_of_view.depth import (
    FOOTPRINT,
    Station,
    angles,
    build_image,
    facing_normals,
    pixel_cells,
    window_votes,
)
from gdt_pipeline.region_of_view.depth_view import depth_images
from gdt_pipeline.region_of_view.window_kernel import window_sides
from gdt_pipeline.simulation.scanner import ScannerSpec, simulate_scan

EYE = np.zeros(3)
K = 3.0


def _scan() -> tuple[np.ndarray, np.ndarray]:
    """A wall 3 m ahead scanned from the origin, with an anisotropic covariance per point."""
    wall = trimesh.creation.box(extents=(0.02, 2.0, 2.0))
    wall.apply_translation((3.0, 0.0, 0.0))
    spec = ScannerSpec(fov_deg=30.0, aspect=1.0, points_per_m2=4000.0, max_range=10.0, profile="tof_low_cost")
    scan = simulate_scan([wall], EYE, np.array([3.0, 0.0, 0.0]), spec, np.random.default_rng(5))
    d = scan.clean / np.linalg.norm(scan.clean, axis=1, keepdims=True)
    dd = d[:, :, None] * d[:, None, :]
    cov = scan.sigma_range[:, None, None] ** 2 * dd + scan.sigma_lateral[:, None, None] ** 2 * (np.eye(3) - dd)
    return scan.points, GaussianUncertainty(cov).cov


def _facets(rng: np.random.Generator) -> np.ndarray:
    """Small turned triangles at the wall (present), in front of it (seen through) and behind it (hidden)."""
    out = []
    for depth in (2.99, 2.6, 3.4):
        centre = np.column_stack([np.full(300, depth), rng.uniform(-0.6, 0.6, (300, 2))])
        corners = rng.normal(0, 0.02, (300, 3, 3))
        corners[:, :, 0] *= 0.2  # roughly facing the station
        out.append(centre[:, None, :] + corners)
    return np.concatenate(out)


def _reference(img, pos: np.ndarray, cov: np.ndarray, tris: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Counts (front, at, behind) and pooled sums per sample, one sample and one window point at a time."""
    az, el, depth = angles(img.frame, img.eye, pos)
    normals, judged = facing_normals(img.eye, pos, depth, tris)
    cells = {key: i for i, key in enumerate(img.keys)}
    counts, pooled = np.zeros((3, len(pos)), dtype=np.int64), np.zeros((2, len(pos)))
    for s in np.flatnonzero(judged):
        n = normals[s]
        var_e = n @ cov[s] @ n
        for drow in (-1, 0, 1):
            for dcol in (-1, 0, 1):
                key = pixel_cells(az[s:s + 1], el[s:s + 1], img.pixel, drow, dcol)[0][0]
                if key not in cells:
                    continue
                sums = np.zeros(2)
                for i in img.order[img.bounds[cells[key]]:img.bounds[cells[key] + 1]]:
                    p = img.points[i]
                    if tris is not None and not _ray_meets_facet(p, tris[s], FOOTPRINT * img.pixel * depth[s]):
                        continue
                    c = img.cov[i]
                    offset, var_p = n @ (p - pos[s]), n @ c @ n
                    tol = K * np.sqrt(var_p + var_e)
                    side = 0 if offset > tol else (2 if offset < -tol else 1)
                    counts[side, s] += 1
                    if side:
                        sums += (offset, var_p)
                pooled[:, s] += sums
    return counts, pooled


def _ray_meets_facet(p: np.ndarray, tri: np.ndarray, margin: float) -> bool:
    """Whether the ray from the eye through p meets the facet's plane within ``margin`` of every edge's line
    (distances from the edges by cross products, a different derivation from the kernel's inward normals)."""
    normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    ray = p - EYE
    t = normal @ (tri[0] - EYE) / (normal @ ray)
    if not t > 0:
        return False
    meet = EYE + t * ray
    unit = normal / np.linalg.norm(normal)
    for i in range(3):
        a, b, c = tri[i], tri[(i + 1) % 3], tri[(i + 2) % 3]
        edge = b - a
        inside_sign = np.sign(np.cross(edge, c - a) @ unit)
        distance = inside_sign * (np.cross(edge, meet - a) @ unit) / np.linalg.norm(edge)
        if distance < -margin:
            return False
    return True


def test_window_kernel_matches_the_reference() -> None:
    pts, cov = _scan()
    station = Station(eye=EYE, contains=lambda p: np.ones(len(p), bool), datasets=(0,), free_range=0.0)
    img = build_image(station, pts, cov, 1.0)
    rng = np.random.default_rng(9)
    tris = _facets(rng)
    pos = tris.mean(axis=1)
    sample_cov = np.broadcast_to(np.eye(3) * 1e-6, (len(pos), 3, 3)).copy()
    want_counts, want_pooled = _reference(img, pos, sample_cov, tris)
    az, el, depth = angles(img.frame, img.eye, pos)
    normals, judged = facing_normals(img.eye, pos, depth, tris)
    cells = np.column_stack([pixel_cells(az, el, img.pixel, r, c)[0] for r in (-1, 0, 1) for c in (-1, 0, 1)])
    counts, pooled = np.zeros((3, len(pos)), dtype=np.int64), np.zeros((2, len(pos)))
    var_e = np.einsum("ij,ijk,ik->i", normals, sample_cov, normals)
    window_sides(cells, judged, pos, normals, tris, FOOTPRINT * img.pixel * depth, var_e, img.eye, img.keys,
                 img.bounds, img.order, img.points, img.cov, K, counts, pooled)
    assert np.array_equal(counts, want_counts)
    assert np.allclose(pooled, want_pooled, rtol=1e-12, atol=1e-18)
    # the three layers come out as they should: at the wall mostly "at", in front "behind", behind it "in front"
    layer = np.repeat(np.arange(3), 300)
    front, at, behind = counts
    assert at[layer == 0].sum() > 5 * (front[layer == 0].sum() + behind[layer == 0].sum())
    assert behind[layer == 1].sum() > 5 * at[layer == 1].sum()
    assert front[layer == 2].sum() > 5 * at[layer == 2].sum()
    # point samples: every point of the window counts; window_votes runs the same kernel
    votes = window_votes(img, pts[::50], cov[::50], None, K)
    assert votes.shape == (2, len(pts[::50])) and votes[0].sum() > 0.9 * len(pts[::50])


def test_depth_image_keeps_the_scans_own_arrays() -> None:
    """A station's image lists the scan's points by pixel instead of copying them (72 B a point): its points and
    covariances are the dataset's arrays, every point is listed once, and each pixel holds exactly its points."""
    pts, cov = _scan()
    scan = Dataset("scan", "as-is", pts, viewpoints=EYE[None]).with_uncertainty(GaussianUncertainty(cov))
    station = Station(eye=EYE, contains=lambda p: np.ones(len(p), bool), datasets=(0,), free_range=0.0)
    img = depth_images([station], [scan], 1.0)[0]
    assert np.shares_memory(img.points, scan.points) and np.shares_memory(img.cov, scan.uncertainty.cov)
    assert img.keys.nbytes + img.bounds.nbytes + img.order.nbytes <= 16 * len(pts)
    assert np.array_equal(np.sort(img.order), np.arange(len(pts)))
    az, el, _ = angles(img.frame, img.eye, pts)
    per_pixel = np.repeat(img.keys, np.diff(img.bounds))
    assert np.array_equal(pixel_cells(az, el, img.pixel)[0][img.order], per_pixel)
    assert np.all(np.diff(img.keys) > 0)
