"""Positional uncertainty per element: Gaussian (full covariance), uniform box (GUM error limits) and
mixtures, each with its 99 % region, sampling and density."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from .arrays import broadcast_rows, frozen_array

CHI2_3_99 = 11.344866730144373  # chi-square quantile, 3 degrees of freedom, p = 0.99 (scipy.stats.chi2.ppf)
BOX_99 = 0.99 ** (1.0 / 3.0)  # a centred box scaled by this holds 99 % of a uniform box's mass


@dataclass(frozen=True)
class Region99:
    """The 99 % probability region of each element's distribution, as offsets from the element's position.

    ``kind`` is "ellipsoid" (``half_axes`` are the radii along the columns of ``axes``), "box" (``half_axes`` are
    half-widths along ``axes``) or "sphere" (``half_axes[:, 0]`` is the radius; a conservative region holding at
    least 99 %, used for mixtures).
    """

    kind: Literal["ellipsoid", "box", "sphere"]
    center: np.ndarray
    half_axes: np.ndarray
    axes: np.ndarray

    def contains(self, offsets: np.ndarray) -> np.ndarray:
        """Whether each ``(n,3)`` offset (point minus element position) lies in its element's region."""
        d = np.asarray(offsets, dtype=np.float64) - self.center
        if self.kind == "sphere":
            return np.linalg.norm(d, axis=-1) <= self.half_axes[..., 0]
        local = np.einsum("nji,nj->ni", self.axes, d)
        scaled = np.divide(local, self.half_axes, out=np.full_like(local, np.inf), where=self.half_axes > 0)
        scaled[(self.half_axes == 0) & (np.abs(local) < 1e-15)] = 0.0
        if self.kind == "box":
            return np.all(np.abs(scaled) <= 1.0, axis=-1)
        return np.einsum("ni,ni->n", scaled, scaled) <= 1.0

    def bounding_radius(self) -> np.ndarray:
        """Radius of a sphere around the element position that holds the whole region (for KD-tree searches)."""
        c = np.linalg.norm(self.center, axis=-1)
        if self.kind == "sphere":
            return c + self.half_axes[..., 0]
        if self.kind == "box":
            return c + np.linalg.norm(self.half_axes, axis=-1)
        return c + self.half_axes.max(axis=-1)


def _psd_factor(cov: np.ndarray) -> np.ndarray:
    """A factor L with L Lᵀ = Σ for symmetric positive semi-definite Σ (eigen-based: works when Σ is singular)."""
    w, v = np.linalg.eigh(cov)
    return v * np.sqrt(np.clip(w, 0.0, None))[..., None, :]


def _gauss_pdf_many(d: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """N(d; 0, C) for ``d (..., S, 3)`` and ``cov (..., 3, 3)``: one factorisation per covariance, S samples each."""
    chol = np.linalg.cholesky(cov)
    inv = np.linalg.inv(chol)
    y = np.einsum("...ij,...sj->...si", inv, d)
    logdet = 2.0 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(axis=-1)
    return np.exp(-0.5 * np.einsum("...si,...si->...s", y, y) - 0.5 * logdet[..., None] - 1.5 * np.log(2 * np.pi))


def _gauss_pdf(d: np.ndarray, cov: np.ndarray) -> np.ndarray:
    chol = np.linalg.cholesky(cov)
    y = np.linalg.solve(chol, d[..., None])[..., 0]
    logdet = 2.0 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(axis=-1)
    return np.exp(-0.5 * np.einsum("...i,...i->...", y, y) - 0.5 * logdet - 1.5 * np.log(2 * np.pi))


@dataclass(frozen=True)
class GaussianUncertainty:
    """Multivariate normal positional uncertainty per element: full 3x3 covariances ``(N,3,3)`` or one ``(1,3,3)``."""

    cov: np.ndarray
    family: Literal["gaussian"] = field(default="gaussian", init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "cov", frozen_array(self.cov, np.float64, (None, 3, 3), "gaussian covariance"))
        if not np.all(np.isfinite(self.cov)):
            raise ValueError("gaussian covariance has non-finite entries")
        if not np.allclose(self.cov, np.swapaxes(self.cov, 1, 2), rtol=1e-9, atol=1e-15):
            raise ValueError("gaussian covariance is not symmetric")

    @classmethod
    def isotropic(cls, sigma: float | np.ndarray) -> GaussianUncertainty:
        """Isotropic covariance sigma² I, for one sigma or one per element."""
        s = np.atleast_1d(np.asarray(sigma, dtype=np.float64))
        return cls(cov=(s**2)[:, None, None] * np.eye(3)[None])

    def covariance(self, n: int) -> np.ndarray:
        """Covariances broadcast to ``(n,3,3)`` (a view when a single one is shared)."""
        broadcast_rows(self.cov, n, "gaussian covariance")
        return np.broadcast_to(self.cov, (n, 3, 3))

    def summary(self, n: int) -> np.ndarray:
        """RMS standard deviation per element, sqrt(trace(Σ)/3): a scalar for display and reports."""
        broadcast_rows(self.cov, n, "gaussian covariance")
        return np.broadcast_to(np.sqrt(np.trace(self.cov, axis1=1, axis2=2) / 3.0), (n,))

    def take(self, idx: np.ndarray) -> GaussianUncertainty:
        """The uncertainty of the elements ``idx`` (a shared covariance stays shared)."""
        if self.cov.shape[0] == 1:
            return self
        # rows of validated covariances need no second check (the symmetry test costs as much as the copy)
        out = object.__new__(GaussianUncertainty)
        cov = self.cov[idx]
        cov.setflags(write=False)
        object.__setattr__(out, "cov", cov)
        return out

    def sample(self, n: int, rng: np.random.Generator, k: int = 1) -> np.ndarray:
        """``k`` random offsets per element, ``(n,k,3)``."""
        factor = np.broadcast_to(_psd_factor(self.cov), (n, 3, 3))
        return np.einsum("nij,nkj->nki", factor, rng.standard_normal((n, k, 3)))

    def pdf(self, offsets: np.ndarray) -> np.ndarray:
        """Density of each element's distribution at an ``(n,3)`` offset from its position."""
        d = np.asarray(offsets, dtype=np.float64)
        return _gauss_pdf(d, self.covariance(len(d)))

    def pdf_many(self, offsets: np.ndarray) -> np.ndarray:
        """Densities at ``(n,S,3)`` offsets, S per element (one factorisation per element)."""
        return _gauss_pdf_many(np.asarray(offsets, dtype=np.float64), self.covariance(len(offsets)))

    def region99(self, n: int) -> Region99:
        """The 99 % ellipsoid of each element (radii from the chi-square quantile with 3 degrees of freedom)."""
        w, v = np.linalg.eigh(self.covariance(n))
        return Region99("ellipsoid", np.zeros((n, 3)), np.sqrt(CHI2_3_99 * np.clip(w, 0.0, None)), v)


@dataclass(frozen=True)
class BoxUncertainty:
    """GUM rectangular error limits per element: uniform in a box of ``half_widths`` turned by ``rotation``.

    ``half_widths`` is ``(N,3)`` or ``(1,3)``; ``rotation`` is ``(N,3,3)``, ``(1,3,3)`` or None for axis-aligned;
    its columns are the box axes in world coordinates.
    """

    half_widths: np.ndarray
    rotation: np.ndarray | None = None
    family: Literal["box"] = field(default="box", init=False)

    def __post_init__(self) -> None:
        hw = frozen_array(self.half_widths, np.float64, (None, 3), "box half-widths")
        object.__setattr__(self, "half_widths", hw)
        if not np.all(np.isfinite(self.half_widths)) or np.any(self.half_widths <= 0):
            raise ValueError("box half-widths must be finite and > 0")
        if self.rotation is not None:
            rot = frozen_array(self.rotation, np.float64, (None, 3, 3), "box rotation")
            eye = np.einsum("nji,njk->nik", rot, rot)
            if not np.allclose(eye, np.eye(3), atol=1e-6):
                raise ValueError("box rotation is not orthonormal")
            object.__setattr__(self, "rotation", rot)

    def covariance(self, n: int) -> np.ndarray:
        """Covariance of the uniform box, R diag(h²/3) Rᵀ, broadcast to ``(n,3,3)``."""
        broadcast_rows(self.half_widths, n, "box half-widths")
        var = np.broadcast_to(self.half_widths**2 / 3.0, (n, 3))
        diag = var[:, :, None] * np.eye(3)[None]
        if self.rotation is None:
            return diag
        rot = np.broadcast_to(self.rotation, (n, 3, 3))
        return rot @ diag @ np.swapaxes(rot, 1, 2)

    def summary(self, n: int) -> np.ndarray:
        """RMS standard deviation of the box per element, sqrt(Σh²/9)."""
        broadcast_rows(self.half_widths, n, "box half-widths")
        return np.broadcast_to(np.sqrt(np.sum(self.half_widths**2, axis=1) / 9.0), (n,))

    def take(self, idx: np.ndarray) -> BoxUncertainty:
        """The uncertainty of the elements ``idx``."""
        hw = self.half_widths if self.half_widths.shape[0] == 1 else self.half_widths[idx]
        rot = None if self.rotation is None else (self.rotation if self.rotation.shape[0] == 1 else self.rotation[idx])
        return BoxUncertainty(hw, rot)

    def axes(self, n: int) -> np.ndarray:
        """Box axes (columns) per element, ``(n,3,3)``."""
        return np.broadcast_to(np.eye(3) if self.rotation is None else self.rotation, (n, 3, 3))

    def sample(self, n: int, rng: np.random.Generator, k: int = 1) -> np.ndarray:
        """``k`` random offsets per element, ``(n,k,3)``, uniform in each box."""
        broadcast_rows(self.half_widths, n, "box half-widths")
        local = rng.uniform(-1.0, 1.0, (n, k, 3)) * np.broadcast_to(self.half_widths, (n, 3))[:, None, :]
        return np.einsum("nij,nkj->nki", self.axes(n), local)

    def pdf(self, offsets: np.ndarray) -> np.ndarray:
        """Density at an ``(n,3)`` offset: 1/volume inside the box, 0 outside."""
        d = np.asarray(offsets, dtype=np.float64)
        n = len(d)
        hw = np.broadcast_to(self.half_widths, (n, 3))
        local = np.einsum("nji,nj->ni", self.axes(n), d)
        inside = np.all(np.abs(local) <= hw, axis=1)
        return np.where(inside, 1.0 / np.prod(2.0 * hw, axis=1), 0.0)

    def pdf_many(self, offsets: np.ndarray) -> np.ndarray:
        """Densities at ``(n,S,3)`` offsets, S per element."""
        d = np.asarray(offsets, dtype=np.float64)
        n = len(d)
        hw = np.broadcast_to(self.half_widths, (n, 3))
        local = np.einsum("nji,nsj->nsi", self.axes(n), d)
        inside = np.all(np.abs(local) <= hw[:, None, :], axis=2)
        return np.where(inside, (1.0 / np.prod(2.0 * hw, axis=1))[:, None], 0.0)

    def region99(self, n: int) -> Region99:
        """The centred box holding 99 % of the mass (half-widths scaled by 0.99^(1/3))."""
        hw = np.broadcast_to(self.half_widths, (n, 3)) * BOX_99
        return Region99("box", np.zeros((n, 3)), hw, np.array(self.axes(n)))


@dataclass(frozen=True)
class MixtureUncertainty:
    """A Gaussian mixture per element: ``weights (N,K)``, component ``means (N,K,3)`` as offsets from the element's
    position, and component ``covs (N,K,3,3)``. The paper merges the neighbours inside a query's 99 % region into
    such a mixture (point-to-point correspondences)."""

    weights: np.ndarray
    means: np.ndarray
    covs: np.ndarray
    family: Literal["mixture"] = field(default="mixture", init=False)

    def __post_init__(self) -> None:
        w = frozen_array(self.weights, np.float64, (None, None), "mixture weights")
        n, k = w.shape
        object.__setattr__(self, "weights", w)
        object.__setattr__(self, "means", frozen_array(self.means, np.float64, (n, k, 3), "mixture means"))
        object.__setattr__(self, "covs", frozen_array(self.covs, np.float64, (n, k, 3, 3), "mixture covariances"))
        if np.any(w < 0) or not np.allclose(w.sum(axis=1), 1.0, atol=1e-9):
            raise ValueError("mixture weights must be >= 0 and sum to 1 per element")

    def mean_offset(self, n: int) -> np.ndarray:
        """Mean of each mixture relative to the element position, ``(n,3)``."""
        broadcast_rows(self.weights, n, "mixture weights")
        return np.broadcast_to(np.einsum("nk,nki->ni", self.weights, self.means), (n, 3))

    def covariance(self, n: int) -> np.ndarray:
        """Covariance of each mixture about its own mean: Σ w (C + μμᵀ) − m mᵀ."""
        broadcast_rows(self.weights, n, "mixture weights")
        m = np.einsum("nk,nki->ni", self.weights, self.means)
        second = np.einsum("nk,nkij->nij", self.weights, self.covs + np.einsum("nki,nkj->nkij", self.means, self.means))
        return np.broadcast_to(second - np.einsum("ni,nj->nij", m, m), (n, 3, 3))

    def summary(self, n: int) -> np.ndarray:
        """RMS standard deviation per element."""
        return np.sqrt(np.trace(self.covariance(n), axis1=1, axis2=2) / 3.0)

    def take(self, idx: np.ndarray) -> MixtureUncertainty:
        """The uncertainty of the elements ``idx``."""
        if self.weights.shape[0] == 1:
            return self
        return MixtureUncertainty(self.weights[idx], self.means[idx], self.covs[idx])

    def _rows(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        broadcast_rows(self.weights, n, "mixture weights")
        k = self.weights.shape[1]
        return (np.broadcast_to(self.weights, (n, k)), np.broadcast_to(self.means, (n, k, 3)),
                np.broadcast_to(self.covs, (n, k, 3, 3)))

    def sample(self, n: int, rng: np.random.Generator, k: int = 1) -> np.ndarray:
        """``k`` random offsets per element, ``(n,k,3)``: a component by weight, then a Gaussian draw from it."""
        w, mu, cov = self._rows(n)
        cum = np.cumsum(w, axis=1)
        comp = (rng.random((n, k, 1)) > cum[:, None, :-1]).sum(axis=2)
        rows = np.arange(n)[:, None]
        factor = _psd_factor(cov[rows, comp])
        return mu[rows, comp] + np.einsum("nkij,nkj->nki", factor, rng.standard_normal((n, k, 3)))

    def pdf(self, offsets: np.ndarray) -> np.ndarray:
        """Density at an ``(n,3)`` offset: Σ w_k N(d; μ_k, C_k)."""
        d = np.asarray(offsets, dtype=np.float64)
        w, mu, cov = self._rows(len(d))
        return np.einsum("nk,nk->n", w, _gauss_pdf(d[:, None, :] - mu, cov))

    def pdf_many(self, offsets: np.ndarray) -> np.ndarray:
        """Densities at ``(n,S,3)`` offsets, S per element (one factorisation per component)."""
        d = np.asarray(offsets, dtype=np.float64)
        w, mu, cov = self._rows(len(d))
        rel = d[:, None, :, :] - mu[:, :, None, :]  # (n, K, S, 3)
        return np.einsum("nk,nks->ns", w, _gauss_pdf_many(rel, cov))

    def region99(self, n: int) -> Region99:
        """A sphere around the element holding at least 99 %: it encloses every component's 99 % ellipsoid."""
        w, mu, cov = self._rows(n)
        lam = np.linalg.eigvalsh(cov)[..., -1]
        radius = np.where(w > 0, np.linalg.norm(mu, axis=-1) + np.sqrt(CHI2_3_99 * np.clip(lam, 0, None)), 0).max(1)
        return Region99("sphere", np.zeros((n, 3)), np.repeat(radius[:, None], 3, axis=1),
                        np.broadcast_to(np.eye(3), (n, 3, 3)).copy())


Uncertainty = GaussianUncertainty | BoxUncertainty | MixtureUncertainty


def uncertainty_rows(u: Uncertainty) -> int:
    """Rows an uncertainty model holds (1: one model shared by every element)."""
    for name in ("cov", "half_widths", "weights"):
        arr = getattr(u, name, None)
        if arr is not None:
            return arr.shape[0]
    raise TypeError(type(u).__name__)


def take_rows(u: Uncertainty, idx: np.ndarray) -> Uncertainty:
    """The rows ``idx`` of an uncertainty model (a shared one-row model stays as it is)."""
    return u if uncertainty_rows(u) == 1 else u.take(idx)
