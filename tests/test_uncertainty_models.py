"""Distribution families: sampled statistics match the declared covariances (10⁵ samples), the 99 % regions hold
99 % of the mass, densities match scipy and integrate to one."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import multivariate_normal

from gdt_pipeline import BoxUncertainty, Dataset, GaussianUncertainty, MixtureUncertainty

N_SAMPLES = 100_000
R = Rotation.from_euler("xyz", [0.4, -0.3, 1.2]).as_matrix()


def _families() -> dict[str, object]:
    cov_aniso = R @ np.diag([4e-4, 2.5e-5, 1e-6]) @ R.T  # a flat, turned ToF-like ellipsoid (20:1 sigma ratio)
    return {
        "gaussian": GaussianUncertainty(np.stack([cov_aniso, np.eye(3) * 1e-4])),
        "box": BoxUncertainty(np.array([[0.002, 0.005, 0.001], [0.01, 0.01, 0.01]]), np.stack([R, np.eye(3)])),
        "mixture": MixtureUncertainty(weights=np.array([[0.2, 0.5, 0.3], [1.0, 0.0, 0.0]]),
                                      means=np.array([[[0.01, 0, 0], [-0.005, 0.004, 0], [0, 0, 0.003]],
                                                      [[0, 0, 0], [5, 5, 5], [5, 5, 5]]]),
                                      covs=np.stack([np.stack([cov_aniso, np.eye(3) * 4e-6, np.eye(3) * 9e-6]),
                                                     np.stack([np.eye(3) * 1e-6] * 3)])),
    }


@pytest.mark.parametrize("name", ["gaussian", "box", "mixture"])
def test_sample_covariance_matches_declared(name: str) -> None:
    fam = _families()[name]
    rng = np.random.default_rng(11)
    samples = fam.sample(2, rng, k=N_SAMPLES)
    assert samples.shape == (2, N_SAMPLES, 3)
    declared = fam.covariance(2)
    mean = fam.mean_offset(2) if name == "mixture" else np.zeros((2, 3))
    for i in range(2):
        emp = np.cov(samples[i].T, bias=True)
        scale = np.sqrt(np.outer(np.diag(declared[i]), np.diag(declared[i])))
        # sampling error of a covariance entry is about sqrt(2/N) of its scale: allow 5 of those
        np.testing.assert_array_less(np.abs(emp - declared[i]) / scale, 5 * np.sqrt(2 / N_SAMPLES) + 1e-12)
        np.testing.assert_allclose(samples[i].mean(axis=0), mean[i], atol=5 * np.sqrt(np.diag(declared[i]).max()
                                                                                   / N_SAMPLES))


@pytest.mark.parametrize("name", ["gaussian", "box", "mixture"])
def test_region99_holds_99_percent(name: str) -> None:
    fam = _families()[name]
    rng = np.random.default_rng(5)
    samples = fam.sample(2, rng, k=N_SAMPLES)
    region = fam.region99(2)
    for i in range(2):
        inside = _contains(region, i, samples[i])
        frac = inside.mean()
        noise = 4 * np.sqrt(0.99 * 0.01 / N_SAMPLES)  # four binomial standard errors
        if name == "mixture":
            assert frac >= 0.99 - noise  # conservative by construction: at least 99 % in expectation
        else:
            assert frac == pytest.approx(0.99, abs=noise)
        assert np.all(np.linalg.norm(samples[i][inside], axis=1) <= region.bounding_radius()[i] + 1e-12)


def _contains(region, i, pts):
    from gdt_pipeline import Region99

    one = Region99(region.kind, np.repeat(region.center[i:i + 1], len(pts), 0),
                   np.repeat(region.half_axes[i:i + 1], len(pts), 0), np.repeat(region.axes[i:i + 1], len(pts), 0))
    return one.contains(pts)


def test_densities() -> None:
    fams = _families()
    rng = np.random.default_rng(2)
    g = fams["gaussian"]
    d = rng.normal(0, 0.01, (2, 3))
    np.testing.assert_allclose(g.pdf(d), [multivariate_normal(np.zeros(3), g.cov[i]).pdf(d[i]) for i in range(2)],
                               rtol=1e-10)
    m = fams["mixture"]
    want = sum(m.weights[0, k] * multivariate_normal(m.means[0, k], m.covs[0, k]).pdf(d[0]) for k in range(3))
    assert m.take(np.array([0])).pdf(d[:1])[0] == pytest.approx(want, rel=1e-10)
    # the box density integrates to one: Monte-Carlo over its bounding cube
    b = BoxUncertainty(np.array([[0.002, 0.005, 0.001]]), R[None])
    half = np.linalg.norm([0.002, 0.005, 0.001])
    pts = rng.uniform(-half, half, (400_000, 3))
    integral = b.pdf(pts).mean() * (2 * half) ** 3
    assert integral == pytest.approx(1.0, rel=0.03)


def test_transform_moves_every_family() -> None:
    t = np.eye(4)
    t[:3, :3] = R
    for fam in _families().values():
        ds = Dataset("d", "as-is", np.zeros((2, 3)), uncertainty=fam)
        moved = ds.transformed(t)
        np.testing.assert_allclose(moved.element_covariance(), R @ fam.covariance(2) @ R.T, atol=1e-15)


def test_mixture_validation() -> None:
    with pytest.raises(ValueError, match="sum to 1"):
        MixtureUncertainty(np.array([[0.5, 0.6]]), np.zeros((1, 2, 3)), np.tile(np.eye(3), (1, 2, 1, 1)))


@pytest.mark.parametrize("name", ["gaussian", "box", "mixture"])
def test_pdf_many_matches_pdf(name: str) -> None:
    fam = _families()[name]
    rng = np.random.default_rng(4)
    offsets = fam.sample(2, rng, k=50)
    many = fam.pdf_many(offsets)
    rows = np.repeat(np.arange(2), 50)
    one = fam.take(rows).pdf(offsets.reshape(-1, 3)).reshape(2, 50)
    np.testing.assert_allclose(many, one, rtol=1e-12)
