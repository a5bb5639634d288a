"""How good a registration is, judged on its finest level: fitness, overlap, the point-to-plane residuals and the
transform's covariance from the point-to-plane normal equations, σ² (JᵀJ)⁻¹ with σ² the residual variance.

Open3D's information matrix is point-to-point: on flat terrain it reports a few millimetres for the horizontal
shift that nothing constrains. The point-to-plane Jacobian J = [x × n, n] has a near-zero column along such a
direction, so its inverse shows it. NaN, or a σ larger than the scene, is an error; a fitness or overlap far too low,
or residuals spread over much of the correspondence distance, is a warning (an error under ``strict``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gdt_pipeline import StageError


@dataclass(frozen=True)
class Limits:
    """When a registration is suspect: the figures below which (or above which) it warns."""

    min_fitness: float
    min_overlap: float
    max_residual_share: float
    strict: bool


@dataclass(frozen=True)
class Fit:
    """The finest level's figures: shares of each side matched, residual spread, pairs, 6x6 covariance (ω, t)."""

    fitness: float
    overlap: float
    residual_sigma: float
    pairs: int
    covariance: np.ndarray
    distance: float

    def sigmas(self) -> tuple[np.ndarray, np.ndarray]:
        """σ of the rotation (degrees) and of the translation (twin units) per axis."""
        diag = np.diag(self.covariance)
        with np.errstate(invalid="ignore"):
            return np.degrees(np.sqrt(diag[:3])), np.sqrt(diag[3:])


def _normals(points: np.ndarray, voxel: float) -> np.ndarray:
    """Unit normals of ``points`` (Open3D, the neighbourhood point_to_plane ICP uses: 2 voxels, 30 points)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    return np.asarray(pcd.normals)


def _down(points: np.ndarray, voxel: float) -> np.ndarray:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(pcd.voxel_down_sample(voxel).points)


def plane_covariance(moved: np.ndarray, target: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-plane residuals of matched pairs and σ² (JᵀJ)⁻¹ over (ω, t), ω about the coordinates' origin."""
    r = np.einsum("ij,ij->i", normals, moved - target)
    jac = np.hstack([np.cross(moved, normals), normals])
    sigma2 = float(r @ r) / max(len(r) - 6, 1)
    try:
        inv = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        inv = np.full((6, 6), np.inf)
    with np.errstate(invalid="ignore", over="ignore"):  # an unconstrained direction: inf or NaN, refused later
        return r, sigma2 * inv


def _matched(points: np.ndarray, tree: cKDTree, distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Which of ``points`` have a point of ``tree`` within ``distance``, and its index."""
    d, j = tree.query(points, distance_upper_bound=distance, workers=-1)
    return np.isfinite(d), j


def assess(fitted: np.ndarray, tgt: np.ndarray, t_local: np.ndarray, voxel: float, distance: float,
           src: np.ndarray) -> Fit:
    """The figures of the local transform ``t_local`` of the ``fitted`` source points onto ``tgt`` (all local) at
    the finest voxel; fitness and overlap over every source point ``src`` (a trimmed fit keeps fewer)."""
    move = t_local[:3, :3].T, t_local[:3, 3]
    g = _down(tgt, voxel)
    tree = cKDTree(g)
    every = _down(src, voxel) @ move[0] + move[1]
    hit, _ = _matched(every, tree, distance)
    fitness = float(hit.mean()) if len(every) else 0.0
    back, _ = _matched(g, cKDTree(every), distance)
    overlap = float(back.mean()) if len(g) else 0.0
    moved = _down(fitted, voxel) @ move[0] + move[1]
    ok, j = _matched(moved, tree, distance)
    if ok.sum() < 6:
        return Fit(fitness, overlap, np.nan, int(ok.sum()), np.full((6, 6), np.nan), distance)
    r, cov = plane_covariance(moved[ok], g[j[ok]], _normals(g, voxel)[j[ok]])
    spread = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    return Fit(fitness, overlap, spread, int(ok.sum()), cov, distance)


def check_covariance(fit: Fit, diagonal: float, method: str, found: list[str]) -> None:
    """Refuse a covariance that is NaN, or whose σ is larger than the scene (bounding-box ``diagonal``); the
    error names what else was ``found`` suspect."""
    sig_rot, sig_t = fit.sigmas()
    also = "".join(f"; {text}" for text in found)
    if not (np.isfinite(sig_rot).all() and np.isfinite(sig_t).all()):
        raise StageError(f"{method}: the transform's covariance is not finite (σ_t {np.round(sig_t, 4).tolist()}, "
                         f"σ_rot {np.round(sig_rot, 4).tolist()} deg, from {fit.pairs} point pairs){also}: the fit is "
                         f"not constrained; give larger `voxels`, an `initial` transform, or check the overlap")
    edge = np.radians(sig_rot) * diagonal / 2  # how far a rotation σ moves the scene's edge
    worst = float(max(sig_t.max(), edge.max()))
    if worst > diagonal:
        raise StageError(f"{method}: the transform's σ is larger than the scene: σ_t {np.round(sig_t, 4).tolist()}, "
                         f"σ_rot {np.round(sig_rot, 4).tolist()} deg ({edge.max():.4g} at the scene's edge) against "
                         f"a bounding-box diagonal of {diagonal:.4g}{also}: the registration did not find a transform")


def suspicions(fit: Fit, limits: Limits) -> list[str]:
    """What is far off in the fit, each naming the figure and its limit (empty when nothing is)."""
    found = []
    if fit.fitness < limits.min_fitness:
        found.append(f"fitness {fit.fitness:.3g} (share of the recent points with a twin point within "
                     f"{fit.distance:.4g}) is below {limits.min_fitness:g}")
    if fit.overlap < limits.min_overlap:
        found.append(f"overlap {fit.overlap:.3g} (share of the twin's points with a recent point within "
                     f"{fit.distance:.4g}) is below {limits.min_overlap:g}")
    if not fit.residual_sigma <= limits.max_residual_share * fit.distance:
        found.append(f"residual spread {fit.residual_sigma:.4g} (1.4826 MAD of the point-to-plane residuals) is over "
                     f"{limits.max_residual_share:g} of the correspondence distance {fit.distance:.4g}")
    return found
