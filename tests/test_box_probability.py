"""The Gaussian–box probability kernel: the bivariate orthants against Owen's T closed form, the trivariate box
probability of every path against Genz quadrature at a high order (an independent method), the error bound holding,
the paths taken where they should be, and the stage reporting the share of pairs per path."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import ndtr, owens_t

from gdt_pipeline import BoxUncertainty
from stages.distance.bhattacharyya_maths import bc_gauss_box
from stages.distance.box_probability import PATHS, box_probability
from stages.distance.normal_orthants import BVN_ERROR, bvn_lower

from .genz_reference import box_prob_genz


def _bvn_owen(h: np.ndarray, k: np.ndarray, r: np.ndarray) -> np.ndarray:
    """P(X < h, Y < k) through Owen's T function (Owen 1956), an independent closed form."""
    q = np.sqrt((1 - r) * (1 + r))
    return (0.5 * (ndtr(h) + ndtr(k)) - owens_t(h, (k - r * h) / (h * q)) - owens_t(k, (h - r * k) / (k * q))
            - 0.5 * (h * k < 0))


def test_bivariate_orthants_match_owens_t() -> None:
    rng = np.random.default_rng(1)
    h, k = rng.normal(0, 2.5, 20_000), rng.normal(0, 2.5, 20_000)
    r = rng.uniform(-0.995, 0.995, 20_000)  # every branch: |r| < 0.3, < 0.75, < 0.925 and beyond
    assert np.max(np.abs(bvn_lower(h, k, r) - _bvn_owen(h, k, r))) < BVN_ERROR
    # independence: the product of the marginals
    assert bvn_lower(np.array([-1.3]), np.array([0.4]), np.array([0.0]))[0] == pytest.approx(ndtr(-1.3) * ndtr(0.4))


def _pairs(n: int, rng: np.random.Generator, spread: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Turned anisotropic Gaussians (σ 0.05–0.3 of the box's half-width) about points in and around a unit box."""
    rot = Rotation.random(n, random_state=rng).as_matrix()
    sig = rng.uniform(0.05, 0.3, (n, 3))
    cov = np.einsum("nij,nj,nkj->nik", rot, sig**2, rot)
    mean = rng.uniform(-spread, spread, (n, 3))
    return mean, cov, np.ones((n, 3))


def _standardised(m: np.ndarray, c: np.ndarray, h: np.ndarray):
    sd = np.sqrt(np.diagonal(c, axis1=1, axis2=2))
    rho = np.stack([c[:, 0, 1] / (sd[:, 0] * sd[:, 1]), c[:, 0, 2] / (sd[:, 0] * sd[:, 2]),
                    c[:, 1, 2] / (sd[:, 1] * sd[:, 2])], 1)
    return (-h - m) / sd, (h - m) / sd, rho


@pytest.mark.parametrize(("spread", "settled_share"), [(0.6, 0.99), (1.3, 0.85)])
def test_box_probability_within_its_bound(spread: float, settled_share: float) -> None:
    """Means inside the box (0.6) or up to 0.3 half-widths beyond it (1.3: corners that are no tails, expanded into
    tail ones)."""
    m, c, h = _pairs(3000, np.random.default_rng(int(spread * 10)), spread)
    lo, hi, rho = _standardised(m, c, h)
    eps = 1e-6
    prob, err, path = box_probability(lo, hi, rho, np.ones(len(m)), eps)
    truth = box_prob_genz(m, c, h, 56)
    settled = path < 2
    assert settled.mean() > settled_share
    # the reported bound holds and is within ε where settled; the reference cuts each outer variable at ±6σ (1e-9 per
    # tail, four tails), so it can sit up to 4e-9 below the truth
    assert np.all(np.abs(prob - truth)[settled] <= err[settled] + 5e-9)
    assert np.all(err[settled] <= eps)
    # unsettled pairs still bracket the truth
    assert np.all(np.abs(prob - truth) <= err + 5e-9)


def test_paths_where_expected() -> None:
    # far outside the box: the screen settles it (P ≈ 0)
    far = box_probability(np.array([[5.0, -3.0, -3.0]]), np.array([[7.0, 3.0, 3.0]]), np.array([[0.4, 0.2, 0.1]]),
                          np.ones(1), 1e-6)
    assert far[2][0] == PATHS.index("bound screen") and far[0][0] < 1e-6
    # crossing one pair of faces only: the one-dimensional normal interval
    one = box_probability(np.array([[-1.0, -9.0, -9.0]]), np.array([[0.5, 9.0, 9.0]]), np.array([[0.5, 0.5, 0.5]]),
                          np.ones(1), 1e-6)
    assert one[2][0] == 0 and one[0][0] == pytest.approx(ndtr(0.5) - ndtr(-1.0), abs=1e-9)
    # crossing every face, turned: inclusion–exclusion
    mid = box_probability(np.array([[-2.5, -2.8, -3.0]]), np.array([[2.9, 2.6, 2.7]]), np.array([[-0.5, -0.45, 0.55]]),
                          np.ones(1), 1e-6)
    assert mid[2][0] == PATHS.index("inclusion–exclusion")


def test_gauss_box_counts_paths_and_stays_exact() -> None:
    rng = np.random.default_rng(4)
    n = 2000
    m, c, _ = _pairs(n, rng, 0.8)
    half = 0.0005
    box = BoxUncertainty(np.full((1, 3), half))
    paths: dict[str, int] = {}
    bc, err = bc_gauss_box(m * half, c * half**2, np.zeros((n, 3)), box, eps=1e-6, paths=paths)
    assert sum(paths.values()) == n and set(paths) <= {"closed form", *PATHS}
    assert np.all(err <= 1e-6)
    # against quadrature in the same frame (X ~ N(μ, 2Σ), BC = scale · P)
    cov2 = 2 * c * half**2
    truth_p = box_prob_genz(m * half, cov2, np.full((n, 3), half), 56)
    scale = (8 * np.pi) ** 0.75 * (np.linalg.det(cov2) / 8) ** 0.25 / (2 * half) ** 1.5
    assert np.max(np.abs(bc - scale * truth_p)) <= 1e-6 + 1e-9


def test_wide_gaussians_keep_their_bound() -> None:
    """Gaussians as wide as the box (a ToF scan against a tight CAD tolerance): corners that are no tails go to
    quadrature, and every pair's reported bound holds against Genz at order 80."""
    n = 4000
    rng = np.random.default_rng(11)
    rot = Rotation.random(n, random_state=rng).as_matrix()
    cov = rot @ np.diag([4e-6, 1e-6, 2.5e-7]) @ np.swapaxes(rot, 1, 2)
    mu, centre = rng.normal(0, 0.001, (n, 3)), rng.normal(0, 0.001, (n, 3))
    box = BoxUncertainty(np.array([[0.002, 0.0015, 0.001]]))
    paths: dict[str, int] = {}
    bc, err = bc_gauss_box(mu, cov, centre, box, eps=1e-6, paths=paths)
    assert paths.get("quadrature", 0) > n / 4 and np.all(err <= 1e-6)
    m, c = mu - centre, 2 * cov
    scale = (8 * np.pi) ** 0.75 * (np.linalg.det(cov)) ** 0.25 / np.sqrt(np.prod(2 * box.half_widths))
    truth = scale * box_prob_genz(m, c, np.broadcast_to(box.half_widths, (n, 3)), 80)
    assert np.all(np.abs(bc - truth) <= err + 5e-9)
