"""Normal orthant probabilities for the Gaussian–box kernel (numba): the standard normal CDF, Genz's BVNU for
bivariate orthants, and trivariate orthants ("corners") by one Gauss–Legendre level over a conditional BVNU.

Why hand-written: scipy's bivariate normal CDF is a per-call quasi-Monte Carlo routine and ``owens_t`` costs ~75 ns a
call; these run inside the per-pair kernel of ``box_probability`` on every core.
"""

from __future__ import annotations

import math

import numpy as np

from gdt_pipeline.compiled import njit, prange

_SQRT_2PI = math.sqrt(2.0 * math.pi)


def _half_nodes(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes in (−1, 0) and their weights (Genz's tables for BVNU are these)."""
    x, w = np.polynomial.legendre.leggauss(order)
    neg = x < 0
    return x[neg].copy(), w[neg].copy()


BVN_ORDERS = (4, 6, 8, 14, 20)  # Gauss–Legendre points of BVNU per |r| band: < 0.3, < 0.5, < 0.75, < 0.925, beyond
BVN_ERROR = 1e-11  # the largest error of those orders, measured against Owen's T over each band (tests)


def _tables() -> np.ndarray:
    """BVNU's Gauss–Legendre half tables, one row (x, w) per order of ``BVN_ORDERS``, padded to 10 columns.

    Genz uses 6, 12 and 20 points for |r| < 0.3, < 0.75 and beyond, for 1e-15; 1e-11 is ample against ε_T ≥ 1e-9,
    and the smaller orders halve the exponentials of the typical pair (|r| 0.4–0.6 between a beam and a box's axes).
    """
    out = np.zeros((len(BVN_ORDERS), 2, 10))
    for row, order in enumerate(BVN_ORDERS):
        x, w = _half_nodes(order)
        out[row, 0, :len(x)], out[row, 1, :len(x)] = x, w
    return out


def legendre_rows(orders: tuple[int, ...]) -> np.ndarray:
    """Gauss–Legendre nodes and weights on [0, 1], one row (x, w) per order, padded: (len(orders), 2, max(orders))."""
    out = np.zeros((len(orders), 2, max(orders)))
    for row, order in enumerate(orders):
        x, w = np.polynomial.legendre.leggauss(order)
        out[row, 0, :order], out[row, 1, :order] = 0.5 * (x + 1.0), 0.5 * w
    return out


# Scratch slots of the per-thread work array the kernels pass down (numba heap allocations per pair cost more than
# the arithmetic): a corner's sines, then an orthant's thresholds and signs; the callers' own slots follow.
WORK_SINES, WORK_ORTHANT, WORK_CALLER, WORK_SIZE = 0, 20, 32, 112
MIN_DECAY = 2.0  # a tail corner is integrated only when its outer variable starts this many σ out
CORNER_ORDERS = (6, 9, 13)  # tried in turn per corner; each difference is the error of the lower order
BVN_TABLES = _tables()
CORNER_NODES = legendre_rows(CORNER_ORDERS)
_TAIL_SPAN = 55.3  # u(2a + u) = 55.3: φ(a + u) / φ(a) = e^-27.6 ≈ 1e-12, where the corner integral is cut


@njit(cache=True)
def phi(x: float) -> float:
    """Standard normal CDF."""
    return 0.5 * math.erfc(-x / math.sqrt(2.0))


@njit(cache=True)
def _row(r: float) -> int:
    """The row of ``_tables`` BVNU uses for correlation r."""
    a = abs(r)
    return 0 if a < 0.3 else (1 if a < 0.5 else (2 if a < 0.75 else (3 if a < 0.925 else 4)))


_SIZES = tuple(o // 2 for o in BVN_ORDERS)


@njit(cache=True)
def _sines(r: float, tables, sn) -> None:
    """The sines BVNU's |r| < 0.925 branch evaluates, which depend on r alone: computed once where many BVNU calls
    share r (a corner integral's nodes)."""
    row = _row(r)
    asr = math.asin(r)
    for i in range(_SIZES[row]):
        x = tables[row, 0, i]
        sn[2 * i] = math.sin(asr * (x + 1.0) / 2.0)
        sn[2 * i + 1] = math.sin(asr * (1.0 - x) / 2.0)


@njit(cache=True)
def _bvnu_shared(dh: float, dk: float, r: float, tables, sn) -> float:
    """``bvnu`` with the sines of ``_sines(r)`` given (|r| < 0.925; otherwise the general path)."""
    if abs(r) >= 0.925:
        return bvnu(dh, dk, r, tables)
    row = _row(r)
    hk = dh * dk
    hs = (dh * dh + dk * dk) / 2.0
    bvn = 0.0
    for i in range(_SIZES[row]):
        a, b = sn[2 * i], sn[2 * i + 1]
        bvn += tables[row, 1, i] * (math.exp((a * hk - hs) / (1.0 - a * a)) + math.exp((b * hk - hs) / (1.0 - b * b)))
    return bvn * math.asin(r) / (4.0 * math.pi) + phi(-dh) * phi(-dk)


@njit(cache=True)
def bvnu_small(h: float, k: float, r: float, tables, tails: float) -> float:
    """BVNU for |r| < 0.925, with Φ(−h)Φ(−k) given (``tails``: the caller often has both)."""
    row = _row(r)
    hk = h * k
    hs = (h * h + k * k) / 2.0
    asr = math.asin(r)
    bvn = 0.0
    for i in range(_SIZES[row]):
        x, w = tables[row, 0, i], tables[row, 1, i]
        sn = math.sin(asr * (x + 1.0) / 2.0)
        bvn += w * math.exp((sn * hk - hs) / (1.0 - sn * sn))
        sn = math.sin(asr * (1.0 - x) / 2.0)
        bvn += w * math.exp((sn * hk - hs) / (1.0 - sn * sn))
    return bvn * asr / (4.0 * math.pi) + tails


@njit(cache=True)
def bvnu(dh: float, dk: float, r: float, tables) -> float:
    """P(X > dh, Y > dk) for a standard bivariate normal with correlation r (Genz 2004, after Drezner–Wesolowsky)."""
    if abs(r) < 0.925:
        return bvnu_small(dh, dk, r, tables, phi(-dh) * phi(-dk))
    x, w = tables[4, 0, :_SIZES[4]], tables[4, 1, :_SIZES[4]]
    h, k = dh, dk
    hk = h * k
    bvn = 0.0
    if r < 0.0:
        k = -k
        hk = -hk
    if abs(r) < 1.0:
        a2 = (1.0 - r) * (1.0 + r)
        a = math.sqrt(a2)
        bs = (h - k) ** 2
        c = (4.0 - hk) / 8.0
        d = (12.0 - hk) / 16.0
        bvn = a * math.exp(-(bs / a2 + hk) / 2.0) * (1.0 - c * (bs - a2) * (1.0 - d * bs / 5.0) / 3.0
                                                   + c * d * a2 * a2 / 5.0)
        if hk > -160.0:
            b = math.sqrt(bs)
            bvn -= math.exp(-hk / 2.0) * _SQRT_2PI * phi(-b / a) * b * (1.0 - c * bs * (1.0 - d * bs / 5.0) / 3.0)
        a = a / 2.0
        for i in range(len(x)):
            for sgn in (-1.0, 1.0):
                xs = (a * (sgn * x[i] + 1.0)) ** 2
                rs = math.sqrt(1.0 - xs)
                bvn += a * w[i] * (math.exp(-bs / (2.0 * xs) - hk / (1.0 + rs)) / rs
                                   - math.exp(-(bs / xs + hk) / 2.0) * (1.0 + c * xs * (1.0 + d * xs)))
        bvn = -bvn / (2.0 * math.pi)
    if r > 0.0:
        return bvn + phi(-max(h, k))
    bvn = -bvn
    if k > h:
        if h < 0.0:
            bvn += phi(k) - phi(h)
        else:
            bvn += phi(-h) - phi(-k)
    return bvn


def bvn_lower(h: np.ndarray, k: np.ndarray, r: np.ndarray) -> np.ndarray:
    """P(X < h, Y < k) of standard bivariate normals with correlation r, element-wise (for tests and callers)."""
    h, k, r = np.broadcast_arrays(np.asarray(h, float), np.asarray(k, float), np.asarray(r, float))
    out = np.empty(h.shape)
    _bvn_many(h.ravel(), k.ravel(), r.ravel(), out.reshape(-1), BVN_TABLES)
    return out


@njit(parallel=True, cache=True)
def _bvn_many(h, k, r, out, tables):
    for i in prange(len(h)):
        out[i] = bvnu(-h[i], -k[i], r[i], tables)


@njit(cache=True)
def _corner(a, r01: float, r02: float, r12: float, tables, nodes, row: int, work) -> float:
    """P(Y₀ ≥ a₀, Y₁ ≥ a₁, Y₂ ≥ a₂) by Gauss–Legendre over the variable with the largest aᵢ (its density decays
    fastest), the other two in closed form (conditional BVNU); ``row`` picks the order."""
    k = 0
    if a[1] > a[k]:
        k = 1
    if a[2] > a[k]:
        k = 2
    i, j = (1, 2) if k == 0 else ((0, 2) if k == 1 else (0, 1))
    r = ((0.0, r01, r02), (r01, 0.0, r12), (r02, r12, 0.0))
    rki, rkj, rij = r[k][i], r[k][j], r[i][j]
    si, sj = math.sqrt(max(1.0 - rki * rki, 1e-300)), math.sqrt(max(1.0 - rkj * rkj, 1e-300))
    rp = min(max((rij - rki * rkj) / (si * sj), -1.0), 1.0)
    a0 = a[k]
    span = -a0 + math.sqrt(a0 * a0 + _TAIL_SPAN)
    order = CORNER_ORDERS[row]
    sn = work[WORK_SINES:WORK_SINES + 20]
    if abs(rp) < 0.925:
        _sines(rp, tables, sn)
    total = 0.0
    for q in range(order):
        y = a0 + span * nodes[row, 0, q]
        inner = _bvnu_shared((a[i] - rki * y) / si, (a[j] - rkj * y) / sj, rp, tables, sn)
        total += nodes[row, 1, q] * math.exp(-0.5 * y * y) * inner
    return total * span / _SQRT_2PI


@njit(cache=True)
def corner_bound(a0: float, a1: float, a2: float, r01: float, r02: float, r12: float) -> float:
    """Upper bound of P(Y ≥ a) for standard Y with correlations r (all aᵢ > 0): P(wᵀY ≥ wᵀa) for w = R⁻¹a when that
    is non-negative (the tightest such half-space), else w = a."""
    # adjugate of R (symmetric, unit diagonal)
    c00, c11, c22 = 1.0 - r12 * r12, 1.0 - r02 * r02, 1.0 - r01 * r01
    c01, c02, c12 = r02 * r12 - r01, r01 * r12 - r02, r01 * r02 - r12
    det = c00 + r01 * c01 + r02 * c02
    best = 1.0
    if det > 1e-12:
        w0 = (c00 * a0 + c01 * a1 + c02 * a2) / det
        w1 = (c01 * a0 + c11 * a1 + c12 * a2) / det
        w2 = (c02 * a0 + c12 * a1 + c22 * a2) / det
        if w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0:
            q = a0 * w0 + a1 * w1 + a2 * w2
            best = phi(-math.sqrt(max(q, 0.0)))
    num = a0 * a0 + a1 * a1 + a2 * a2
    var = num + 2.0 * (r01 * a0 * a1 + r02 * a0 * a2 + r12 * a1 * a2)
    if var > 0.0:
        best = min(best, phi(-num / math.sqrt(var)))
    return best


@njit(cache=True)
def _tail_corner(a, r01: float, r02: float, r12: float, tables, nodes, budget: float, work) -> tuple[float, float]:
    """P(Y ≥ a) for all aᵢ ≥ 0 (a true tail corner) and its error: successive orders of ``_corner`` until their
    difference is within ``budget``, or the last ones'."""
    if max(a[0], a[1], a[2]) < MIN_DECAY:
        # the integrand decays too slowly from the start for successive orders to bound the error (measured: 2e-5
        # claimed as 6e-7 with a spread as wide as the box): no answer, the pair goes to Genz quadrature
        return 0.0, np.inf
    coarse = _corner(a, r01, r02, r12, tables, nodes, 0, work)
    fine = _corner(a, r01, r02, r12, tables, nodes, 1, work)
    row = 1
    while abs(fine - coarse) > budget and row + 1 < len(CORNER_ORDERS):
        row += 1
        coarse, fine = fine, _corner(a, r01, r02, r12, tables, nodes, row, work)
    return fine, abs(fine - coarse)


@njit(cache=True)
def orthant(a, r01: float, r02: float, r12: float, tables, nodes, budget: float, work) -> tuple[float, float]:
    """P(Y₀ ≥ a₀, Y₁ ≥ a₁, Y₂ ≥ a₂) and its error, for any signs of a.

    Where the mean lies beyond a face (aⱼ < 0) the corner is no tail: its integrand does not decay from the start
    and successive orders understate the error. Each such {Yⱼ ≥ aⱼ} is written 1 − {−Yⱼ > −aⱼ}, which expands the
    corner into lower orthants (normal tails, BVNU) and one true tail corner."""
    r = ((1.0, r01, r02), (r01, 1.0, r12), (r02, r12, 1.0))
    neg = 0
    for j in range(3):
        if a[j] < 0.0:
            neg |= 1 << j
    total, error = 0.0, 0.0
    t = work[WORK_ORTHANT:WORK_ORTHANT + 3]
    sg = work[WORK_ORTHANT + 3:WORK_ORTHANT + 6]
    for flip in range(8):
        if flip & ~neg:
            continue
        n, sign, d0, d1 = 0, 1.0, 0, 0
        for j in range(3):
            keep = True
            if not (neg >> j) & 1:
                t[n], sg[n] = a[j], 1.0
            elif (flip >> j) & 1:
                t[n], sg[n] = -a[j], -1.0
                sign = -sign
            else:
                keep = False
            if keep:
                if n == 0:
                    d0 = j
                elif n == 1:
                    d1 = j
                n += 1
        if n == 0:
            value, err = 1.0, 0.0
        elif n == 1:
            value, err = phi(-t[0]), 0.0
        elif n == 2:
            value = bvnu(t[0], t[1], sg[0] * sg[1] * r[d0][d1], tables)
            err = BVN_ERROR
        else:
            value, err = _tail_corner(t, sg[0] * sg[1] * r01, sg[0] * sg[2] * r02, sg[1] * sg[2] * r12, tables,
                                      nodes, budget, work)
        total += sign * value
        error += err
    return total, error
