"""Closed forms for many symmetric 3x3 matrices at once (covariances): faster than ``np.linalg`` on (N,3,3)."""

from __future__ import annotations

import numpy as np


def sym3(c: np.ndarray) -> tuple[np.ndarray, ...]:
    """The six distinct entries xx xy xz yy yz zz of symmetric ``(N,3,3)`` matrices."""
    return c[:, 0, 0], c[:, 0, 1], c[:, 0, 2], c[:, 1, 1], c[:, 1, 2], c[:, 2, 2]


def det3(c: np.ndarray) -> np.ndarray:
    """Determinants of symmetric 3x3 matrices ``(N,3,3)``."""
    a, b, cc, d, e, f = sym3(c)
    return a * (d * f - e * e) - b * (b * f - cc * e) + cc * (b * e - cc * d)


def _adjugate(c: np.ndarray) -> tuple[np.ndarray, ...]:
    """The six distinct entries A B C D E F (xx xy xz yy yz zz) of the adjugates of symmetric ``(N,3,3)`` matrices,
    and their determinants."""
    a, b, cc, d, e, f = sym3(c)
    A, B, C = d * f - e * e, cc * e - b * f, b * e - cc * d
    D, E, F = a * f - cc * cc, b * cc - a * e, a * d - b * b
    return A, B, C, D, E, F, a * A + b * B + cc * C


def inv3(c: np.ndarray) -> np.ndarray:
    """Inverses of symmetric 3x3 matrices ``(N,3,3)`` via the adjugate (no per-matrix LAPACK call)."""
    A, B, C, D, E, F, det = _adjugate(c)
    return np.stack([np.stack([A, B, C], -1), np.stack([B, D, E], -1), np.stack([C, E, F], -1)], -2) / det[:, None,
                                                                                                             None]


def quad_inv3(c: np.ndarray, x: np.ndarray) -> np.ndarray:
    """xᵀ C⁻¹ x for symmetric 3x3 ``C`` via the adjugate (N pairs at once)."""
    A, B, C, D, E, F, det = _adjugate(c)
    x0, x1, x2 = x[:, 0], x[:, 1], x[:, 2]
    num = A * x0 * x0 + D * x1 * x1 + F * x2 * x2 + 2 * (B * x0 * x1 + C * x0 * x2 + E * x1 * x2)
    return num / det
