"""P(X ∈ box) for a trivariate normal X, per pair, at closed-form cost wherever the answer is exact within ε (numba).

In the box's frame and standardised, X's coordinate i must lie in [loᵢ, hiᵢ]. Let Aᵢ⁻ = {Zᵢ < loᵢ} and
Aᵢ⁺ = {Zᵢ > hiᵢ} be the six "outside one face" events. Opposite faces cannot both hold, so at most three events
(one per axis) hold at once and inclusion–exclusion ends at the third order, exactly:

    P(box) = 1 − S₁ + S₂ − S₃,

S₁ the six normal tails, S₂ the twelve bivariate orthants of faces on different axes (Genz's BVNU algorithm, within
1e-11), S₃ the eight trivariate corners. Each corner is bounded above by the least of its three pair orthants and by a
half-space bound (the corner lies in {wᵀY ≥ wᵀa} for any w ≥ 0, a normal tail); a corner whose bound matters is
integrated (one Gauss–Legendre level over a conditional BVNU, successive orders for its error), so

    1 − S₁ + S₂ − S₃⁺ ≤ P ≤ 1 − S₁ + S₂ − S₃⁻.

Paths, per pair, cheapest first:

0. bound screen: max(0, Σpᵢ − 2) ≤ P ≤ min pᵢ over the three marginal interval probabilities. This settles pairs far
   outside the box (P ≈ 0) and pairs whose spread crosses only one pair of opposite faces (P ≈ that axis' pᵢ: the
   one-dimensional normal interval, its error bounded by the other axes' tails).
1. inclusion–exclusion as above, when the bracket is within ε.
2. neither: the caller integrates numerically (Genz quadrature).
3. closed form: the Gaussian's axes are the box's (a product of three normal intervals).

The orthants are ``normal_orthants``; this kernel does the screens, the twelve orthants and the corners of a pair in
one pass, on every core.
"""

from __future__ import annotations

import math

import numpy as np

from gdt_pipeline.compiled import njit, prange

from .normal_orthants import (
    BVN_ERROR,
    BVN_TABLES,
    CORNER_NODES,
    WORK_CALLER,
    WORK_SIZE,
    bvnu,
    bvnu_small,
    corner_bound,
    legendre_rows,
    orthant,
    phi,
)

PATHS = ("bound screen", "inclusion–exclusion", "quadrature", "closed form")
K_SQRT = (8.0 * np.pi) ** 0.75
_SQRT_2PI = math.sqrt(2.0 * math.pi)


@njit(cache=True)
def _interval(lo: float, hi: float) -> float:
    """Φ(hi) − Φ(lo) without cancellation in the upper tail."""
    return max(phi(hi) - phi(lo), 0.0) if lo < 0.0 else max(phi(-lo) - phi(-hi), 0.0)


@njit(cache=True)
def _settle(lo, hi, rho, scale: float, eps: float, tables, nodes, work) -> tuple[float, float, int]:
    """One pair: P(lo ≤ Z ≤ hi) for standard Z with correlations rho (r₀₁, r₀₂, r₁₂), its error bound and path."""
    ax = (0, 1, 2, 0, 1, 2)
    sg = (1.0, 1.0, 1.0, -1.0, -1.0, -1.0)
    b = work[WORK_CALLER:WORK_CALLER + 6]
    t = work[WORK_CALLER + 6:WORK_CALLER + 12]
    pair = work[WORK_CALLER + 12:WORK_CALLER + 48]  # 6 × 6, row-major
    a = work[WORK_CALLER + 48:WORK_CALLER + 51]
    p_min, p_sum = 1.0, 0.0
    for axis in range(3):
        b[axis], b[axis + 3] = lo[axis], -hi[axis]
        t[axis], t[axis + 3] = phi(lo[axis]), phi(-hi[axis])
        p_ax = _interval(lo[axis], hi[axis])
        p_min = min(p_min, p_ax)
        p_sum += p_ax
    low, up = max(0.0, p_sum - 2.0), p_min
    if scale * (up - low) <= 2.0 * eps:
        return 0.5 * (low + up), 0.5 * (up - low), 0
    s1 = t[0] + t[1] + t[2] + t[3] + t[4] + t[5]
    s2 = 0.0
    for f in range(6):
        for g in range(f + 1, 6):
            if ax[f] == ax[g]:
                continue
            r = sg[f] * sg[g] * rho[ax[f] + ax[g] - 1]
            if abs(r) < 0.925:  # Φ(b_f)Φ(b_g) are the two tails already at hand
                v = max(bvnu_small(-b[f], -b[g], r, tables, t[f] * t[g]), 0.0)
            else:
                v = max(bvnu(-b[f], -b[g], r, tables), 0.0)
            pair[6 * f + g] = pair[6 * g + f] = v
            s2 += v
    s3_lo, s3_hi = 0.0, 0.0
    for f in (0, 3):
        for g in (1, 4):
            for h in (2, 5):
                bound = min(pair[6 * f + g], pair[6 * f + h], pair[6 * g + h])
                a[0], a[1], a[2] = -b[f], -b[g], -b[h]
                c01, c02, c12 = sg[f] * sg[g] * rho[0], sg[f] * sg[h] * rho[1], sg[g] * sg[h] * rho[2]
                if a[0] > 0.0 and a[1] > 0.0 and a[2] > 0.0:
                    bound = min(bound, corner_bound(a[0], a[1], a[2], c01, c02, c12))
                if scale * bound <= eps / 8.0:
                    s3_hi += bound
                    continue
                value, gap = orthant(a, c01, c02, c12, tables, nodes, eps / (8.0 * scale), work)
                s3_lo += max(value - gap, 0.0)
                s3_hi += min(value + gap, bound)
    top = min(1.0 - s1 + s2 - s3_lo, up)
    bottom = max(1.0 - s1 + s2 - s3_hi, low)
    # twelve orthants and at most two orders of a corner's nodes, each BVNU within BVN_ERROR
    err = 0.5 * max(top - bottom, 0.0) + 40.0 * BVN_ERROR
    return 0.5 * (top + bottom), err, 1 if scale * err <= eps else 2


_BLOCK = 256  # pairs per work array


@njit(parallel=True, cache=True)
def _standard_kernel(lo, hi, rho, scale, eps, prob, err, path, tables, nodes):
    n = lo.shape[0]
    for blk in prange((n + _BLOCK - 1) // _BLOCK):
        work = np.empty(WORK_SIZE)
        for i in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            prob[i], err[i], path[i] = _settle(lo[i], hi[i], rho[i], scale[i], eps, tables, nodes, work)


@njit(cache=True)
def _one_gauss_box(mu, cov, center, R, h, eps, tables, nodes, work) -> tuple[float, float, int]:
    """One pair: X ~ N(μ, 2Σ) in the box's frame (R's columns), standardised, then ``_settle``; BC = scale · P."""
    std = work[WORK_CALLER + 51:WORK_CALLER + 60]  # lo, hi, rho
    m = work[WORK_CALLER + 60:WORK_CALLER + 63]
    c = work[WORK_CALLER + 63:WORK_CALLER + 72].reshape((3, 3))
    for k in range(3):
        m[k] = 0.0
        for j in range(3):
            m[k] += R[j, k] * (mu[j] - center[j])
    for k in range(3):
        for col in range(k, 3):
            v = 0.0
            for p in range(3):
                for q in range(3):
                    v += R[p, k] * cov[p, q] * R[q, col]
            c[k, col] = c[col, k] = 2.0 * v
    det = (c[0, 0] * (c[1, 1] * c[2, 2] - c[1, 2] * c[2, 1]) - c[0, 1] * (c[1, 0] * c[2, 2] - c[1, 2] * c[2, 0])
           + c[0, 2] * (c[1, 0] * c[2, 1] - c[1, 1] * c[2, 0]))
    # √|Σ| of the original Gaussian: |2Σ| = 8|Σ|
    scale = K_SQRT * (max(det, 0.0) / 8.0) ** 0.25 / np.sqrt(8.0 * h[0] * h[1] * h[2])
    for k in range(3):
        sd = np.sqrt(c[k, k])
        std[k], std[3 + k] = (-h[k] - m[k]) / sd, (h[k] - m[k]) / sd
    std[6] = c[0, 1] / np.sqrt(c[0, 0] * c[1, 1])
    std[7] = c[0, 2] / np.sqrt(c[0, 0] * c[2, 2])
    std[8] = c[1, 2] / np.sqrt(c[1, 1] * c[2, 2])
    if abs(std[6]) <= 1e-12 and abs(std[7]) <= 1e-12 and abs(std[8]) <= 1e-12:
        return scale * _interval(std[0], std[3]) * _interval(std[1], std[4]) * _interval(std[2], std[5]), 0.0, 3
    p, e, path = _settle(std[0:3], std[3:6], std[6:9], scale, eps, tables, nodes, work)
    return scale * p, scale * e, path


@njit(parallel=True, cache=True)
def _gauss_box_kernel(mu, cov, center, axes, half, eps, bc, err, path, tables, nodes):
    n = mu.shape[0]
    shared_axes, shared_half = axes.shape[0] == 1, half.shape[0] == 1
    for blk in prange((n + _BLOCK - 1) // _BLOCK):
        work = np.empty(WORK_SIZE)
        for i in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            bc[i], err[i], path[i] = _one_gauss_box(mu[i], cov[i], center[i], axes[0] if shared_axes else axes[i],
                                                    half[0] if shared_half else half[i], eps, tables, nodes, work)


def box_probability(lo: np.ndarray, hi: np.ndarray, rho: np.ndarray, scale: np.ndarray, eps: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """P(lo ≤ Z ≤ hi) for standard trivariate normals Z with correlations ``rho`` (columns r₀₁, r₀₂, r₁₂): the value,
    its error bound and the path taken (index into ``PATHS``). Path 2 means "not settled within ε / scale": its
    value is only the midpoint of the bounds, for the caller to integrate."""
    n = len(lo)
    prob, err = np.empty(n), np.empty(n)
    path = np.empty(n, dtype=np.int8)
    _standard_kernel(np.ascontiguousarray(lo, dtype=np.float64), np.ascontiguousarray(hi, dtype=np.float64),
                     np.ascontiguousarray(rho, dtype=np.float64), np.ascontiguousarray(scale, dtype=np.float64),
                     float(eps), prob, err, path, BVN_TABLES, CORNER_NODES)
    return prob, err, path


def gauss_box_bc(mu: np.ndarray, cov: np.ndarray, center: np.ndarray, axes: np.ndarray, half: np.ndarray,
                 eps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bhattacharyya coefficients of Gaussians N(μ, Σ) against uniform boxes (centre, axes as columns, half-widths;
    axes and half-widths one row per pair or one shared row), their error bounds and paths (``PATHS``). Path-2 pairs
    hold only the midpoint of their bounds, for the caller to integrate."""
    n = len(mu)
    bc, err = np.empty(n), np.empty(n)
    path = np.empty(n, dtype=np.int8)
    f64 = np.float64
    _gauss_box_kernel(np.ascontiguousarray(mu, f64), np.ascontiguousarray(cov, f64), np.ascontiguousarray(center, f64),
                      np.ascontiguousarray(axes, f64), np.ascontiguousarray(half, f64), float(eps), bc, err, path,
                      BVN_TABLES, CORNER_NODES)
    return bc, err, path


GENZ_ORDERS = (10, 14, 20, 28, 40, 56)  # Gauss–Legendre orders tried in turn per pair; the cost grows with order²
_Z_CUT = 6.0  # each outer variable is cut at ±6: one tail beyond holds 1e-9


_GENZ_NODES = legendre_rows(GENZ_ORDERS)


@njit(cache=True)
def _genz_one(a, b, L, nodes, row: int) -> float:
    """P(a ≤ L z ≤ b) for standard z, by Genz's sequential conditioning: Gauss–Legendre over the first two
    standardised variables (each cut at ±6), the third in closed form."""
    order = GENZ_ORDERS[row]
    lo1 = min(max(a[0] / L[0, 0], -_Z_CUT), _Z_CUT)
    hi1 = min(max(b[0] / L[0, 0], -_Z_CUT), _Z_CUT)
    total = 0.0
    for q in range(order):
        z1 = lo1 + (hi1 - lo1) * nodes[row, 0, q]
        w1 = (hi1 - lo1) * nodes[row, 1, q] * math.exp(-0.5 * z1 * z1) / _SQRT_2PI
        lo2 = min(max((a[1] - L[1, 0] * z1) / L[1, 1], -_Z_CUT), _Z_CUT)
        hi2 = min(max((b[1] - L[1, 0] * z1) / L[1, 1], -_Z_CUT), _Z_CUT)
        inner = 0.0
        for r in range(order):
            z2 = lo2 + (hi2 - lo2) * nodes[row, 0, r]
            w2 = (hi2 - lo2) * nodes[row, 1, r] * math.exp(-0.5 * z2 * z2) / _SQRT_2PI
            shift = L[2, 0] * z1 + L[2, 1] * z2
            inner += w2 * _interval((a[2] - shift) / L[2, 2], (b[2] - shift) / L[2, 2])
        total += w1 * inner
    return total


@njit(parallel=True, cache=True)
def _genz_kernel(m, c, h, scale, eps, prob, err, nodes):
    for i in prange(m.shape[0]):
        # narrowest interval (in standard deviations) first
        perm = np.argsort(h[i] / np.sqrt(np.array([c[i, 0, 0], c[i, 1, 1], c[i, 2, 2]])))
        cp = np.empty((3, 3))
        for j in range(3):
            for k in range(3):
                cp[j, k] = c[i, perm[j], perm[k]]
        L = np.linalg.cholesky(cp)
        a = np.array([-h[i, perm[j]] - m[i, perm[j]] for j in range(3)])
        b = np.array([h[i, perm[j]] - m[i, perm[j]] for j in range(3)])
        prev = _genz_one(a, b, L, nodes, 0)
        prob[i], err[i] = prev, 0.0
        for row in range(1, len(GENZ_ORDERS)):
            cur = _genz_one(a, b, L, nodes, row)
            prob[i], err[i] = cur, abs(cur - prev) * scale[i]
            if err[i] <= eps:
                break
            prev = cur


def genz_box_probability(m: np.ndarray, c: np.ndarray, h: np.ndarray, scale: np.ndarray, eps: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """P(−h ≤ X ≤ h) for X ~ N(m, C) by Genz quadrature, the order raised per pair until two successive orders
    agree to ``eps`` after multiplying by ``scale`` (the BC factor); the value and that last difference."""
    n = len(m)
    prob, err = np.empty(n), np.empty(n)
    f64 = np.float64
    _genz_kernel(np.ascontiguousarray(m, f64), np.ascontiguousarray(c, f64), np.ascontiguousarray(h, f64),
                 np.ascontiguousarray(scale, f64), float(eps), prob, err, _GENZ_NODES)
    return prob, err
