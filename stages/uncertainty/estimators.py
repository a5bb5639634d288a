"""Vectorised estimators behind the uncertainty stages: sensor-model covariances, voxel MLE, registration
propagation. Plain functions on arrays, so benchmarks and tests can call them directly."""

from __future__ import annotations

import numpy as np


def beam_covariances(points: np.ndarray, origin: np.ndarray, sigma_range: np.ndarray, sigma_lateral: np.ndarray
                     ) -> np.ndarray:
    """Σ = σ_r² d dᵀ + σ_l² (I − d dᵀ) per point, with d the unit beam direction from ``origin``."""
    d = np.asarray(points, dtype=np.float64) - origin
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    outer = np.einsum("ni,nj->nij", d, d)
    sr2 = (np.asarray(sigma_range) ** 2)[:, None, None]
    sl2 = (np.asarray(sigma_lateral) ** 2)[:, None, None]
    return sr2 * outer + sl2 * (np.eye(3)[None] - outer)


def voxel_mle(points: np.ndarray, voxel: float, overlap_steps: int, min_points: int, min_sigma: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximum-likelihood Gaussians on an overlapping voxel grid: means ``(M,3)``, covariances ``(M,3,3)``, counts.

    The grid of cubes of edge ``voxel`` (anchored at multiples of ``voxel``) is laid ``overlap_steps`` times per
    axis, shifted by voxel/overlap_steps, so
    every point falls in ``overlap_steps³`` voxels (overlap 1 − 1/overlap_steps). Per voxel with at least
    ``min_points`` points: mean and the MLE covariance (divided by n, not n − 1). Eigenvalues are raised to at
    least ``min_sigma²``, so flat patches keep a thin but valid Gaussian instead of a singular one.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, dtype=np.int64)
    # Anchored at multiples of the voxel in world coordinates, not at the data's minimum: every epoch and every tile
    # of a dataset then gets the same grid.
    base = np.floor(pts.min(axis=0) / voxel) * voxel
    stride = voxel / overlap_steps
    means, covs, counts = [], [], []
    for sx in range(overlap_steps):
        for sy in range(overlap_steps):
            for sz in range(overlap_steps):
                origin = base - np.array([sx, sy, sz]) * stride
                ijk = np.floor((pts - origin) / voxel).astype(np.int64)
                dims = ijk.max(axis=0) + 1
                keys = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
                uniq, inv, cnt = np.unique(keys, return_inverse=True, return_counts=True)
                # moments relative to each voxel's corner: small numbers, no cancellation for UTM coordinates
                q = pts - (origin + ijk * voxel)
                m = len(uniq)
                s1 = np.stack([np.bincount(inv, q[:, i], minlength=m) for i in range(3)], axis=1)
                s2 = np.empty((m, 3, 3))
                for i in range(3):
                    for j in range(i, 3):
                        s2[:, i, j] = s2[:, j, i] = np.bincount(inv, q[:, i] * q[:, j], minlength=m)
                keep = cnt >= min_points
                n = cnt[keep].astype(np.float64)
                mu_local = s1[keep] / n[:, None]
                cov = s2[keep] / n[:, None, None] - np.einsum("ni,nj->nij", mu_local, mu_local)
                corner_ijk = np.stack([uniq[keep] // (dims[1] * dims[2]), (uniq[keep] // dims[2]) % dims[1],
                                       uniq[keep] % dims[2]], axis=1)
                means.append(origin + corner_ijk * voxel + mu_local)
                covs.append(cov)
                counts.append(cnt[keep])
    mean = np.concatenate(means)
    cov = np.concatenate(covs)
    w, v = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, 1, 2)))
    w = np.maximum(w, min_sigma**2)
    cov = np.einsum("nij,nj,nkj->nik", v, w, v)
    return mean, cov, np.concatenate(counts)


def skew(p: np.ndarray) -> np.ndarray:
    """Cross-product matrices [p]× of ``(N,3)`` vectors."""
    z = np.zeros(len(p))
    return np.stack([np.stack([z, -p[:, 2], p[:, 1]], 1), np.stack([p[:, 2], z, -p[:, 0]], 1),
                     np.stack([-p[:, 1], p[:, 0], z], 1)], axis=1)


def propagate_registration(points: np.ndarray, transform_cov: np.ndarray) -> np.ndarray:
    """Covariance each point gets from a rigid transform's 6x6 covariance (order: rotation ωx ωy ωz, translation).

    First order: x' = x + ω × x + t, so J = [−[x]×, I] and Σ_x = J Σ_T Jᵀ (as in M3C2-EP).
    """
    jac = np.concatenate([-skew(np.asarray(points, dtype=np.float64)), np.broadcast_to(np.eye(3), (len(points), 3,
                                                                                                    3))], axis=2)
    return np.einsum("nij,jk,nlk->nil", jac, transform_cov, jac)
