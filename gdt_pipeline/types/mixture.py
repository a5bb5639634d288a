"""The Gaussian mixture model of positional uncertainty per element (point-to-point correspondences merge the
neighbours inside a query's 99 % region into one); its operations as the other models' (``uncertainty.py``)."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np

from .arrays import broadcast_rows, covariance6, frozen_array
from .densities import gauss_pdf, gauss_pdf_many, psd_factor
from .region99 import CHI2_3_99, Region99

if TYPE_CHECKING:
    from .uncertainty import GaussianUncertainty


@dataclass(frozen=True)
class MixtureUncertainty:
    """A Gaussian mixture per element: ``weights (N,K)``, component ``means (N,K,3)`` as offsets from the element's
    position, and component ``covs (N,K,3,3)``. The paper merges the neighbours inside a query's 99 % region into
    such a mixture (point-to-point correspondences)."""

    weights: np.ndarray
    means: np.ndarray
    covs: np.ndarray
    model: Literal["mixture"] = field(default="mixture", init=False)

    def __post_init__(self) -> None:
        w = frozen_array(self.weights, np.float64, (None, None), "mixture weights")
        n, k = w.shape
        object.__setattr__(self, "weights", w)
        object.__setattr__(self, "means", frozen_array(self.means, np.float64, (n, k, 3), "mixture means"))
        object.__setattr__(self, "covs", frozen_array(self.covs, np.float64, (n, k, 3, 3), "mixture covariances"))
        if np.any(w < 0) or not np.allclose(w.sum(axis=1), 1.0, atol=1e-9):
            raise ValueError("mixture weights must be >= 0 and sum to 1 per element")

    @property
    def rows(self) -> int:
        """Rows the model holds (1: one mixture shared by every element)."""
        return int(self.weights.shape[0])

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
        return np.asarray(np.sqrt(np.trace(self.covariance(n), axis1=1, axis2=2) / 3.0))

    def take(self, idx: np.ndarray) -> MixtureUncertainty:
        """The uncertainty of the elements ``idx``."""
        if self.weights.shape[0] == 1:
            return self
        return MixtureUncertainty(self.weights[idx], self.means[idx], self.covs[idx])

    def repeated(self, n: int) -> MixtureUncertainty:
        """The model with one row per element of ``n`` (a shared one repeated)."""
        if self.rows == n:
            return self
        return MixtureUncertainty(np.repeat(self.weights, n, axis=0), np.repeat(self.means, n, axis=0),
                                  np.repeat(self.covs, n, axis=0))

    def padded(self, k: int) -> MixtureUncertainty:
        """The same mixtures with ``k`` components, the extra ones weightless (the placeholders point_to_point
        uses)."""
        n, have = self.weights.shape
        if have == k:
            return self
        weights = np.zeros((n, k))
        weights[:, :have] = self.weights
        means = np.zeros((n, k, 3))
        means[:, :have] = self.means
        covs = np.broadcast_to(np.eye(3), (n, k, 3, 3)).copy()
        covs[:, :have] = self.covs
        return MixtureUncertainty(weights, means, covs)

    @staticmethod
    def stacked(parts: Sequence[MixtureUncertainty]) -> MixtureUncertainty:
        """The rows of ``parts`` one after the other, padded to the most components any has."""
        k = max(p.weights.shape[1] for p in parts)
        full = [p.padded(k) for p in parts]
        return MixtureUncertainty(np.concatenate([p.weights for p in full]), np.concatenate([p.means for p in full]),
                                  np.concatenate([p.covs for p in full]))

    def rotated(self, rot: np.ndarray) -> MixtureUncertainty:
        """The model turned by the rotation ``rot`` (3,3): component offsets R·μ and covariances R C Rᵀ."""
        return MixtureUncertainty(self.weights, self.means @ rot.T, rot @ self.covs @ rot.T)

    def moment_matched(self, n: int) -> GaussianUncertainty:
        """The Gaussian of equal covariance (about the mixture's mean), per element."""
        from .uncertainty import GaussianUncertainty

        return GaussianUncertainty(self.covariance(n))

    def stored(self, n: int) -> dict[str, np.ndarray]:
        """What the twin stores of the model for ``n`` elements: its moments (covariance about its mean); the
        components stay in the run."""
        return {"covariance": covariance6(self.covariance(n))}

    def components(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Weights ``(n,K)``, means ``(n,K,3)`` and covariances ``(n,K,3,3)`` broadcast to ``n`` elements."""
        broadcast_rows(self.weights, n, "mixture weights")
        k = self.weights.shape[1]
        return (np.broadcast_to(self.weights, (n, k)), np.broadcast_to(self.means, (n, k, 3)),
                np.broadcast_to(self.covs, (n, k, 3, 3)))

    def sample(self, n: int, rng: np.random.Generator, k: int = 1) -> np.ndarray:
        """``k`` random offsets per element, ``(n,k,3)``: a component by weight, then a Gaussian draw from it."""
        w, mu, cov = self.components(n)
        cum = np.cumsum(w, axis=1)
        comp = (rng.random((n, k, 1)) > cum[:, None, :-1]).sum(axis=2)
        rows = np.arange(n)[:, None]
        factor = psd_factor(cov[rows, comp])
        return np.asarray(mu[rows, comp] + np.einsum("nkij,nkj->nki", factor, rng.standard_normal((n, k, 3))))

    def pdf(self, offsets: np.ndarray) -> np.ndarray:
        """Density at an ``(n,3)`` offset: Σ w_k N(d; μ_k, C_k)."""
        d = np.asarray(offsets, dtype=np.float64)
        w, mu, cov = self.components(len(d))
        return np.asarray(np.einsum("nk,nk->n", w, gauss_pdf(d[:, None, :] - mu, cov)))

    def pdf_many(self, offsets: np.ndarray) -> np.ndarray:
        """Densities at ``(n,S,3)`` offsets, S per element (one factorisation per component)."""
        d = np.asarray(offsets, dtype=np.float64)
        w, mu, cov = self.components(len(d))
        rel = d[:, None, :, :] - mu[:, :, None, :]  # (n, K, S, 3)
        return np.asarray(np.einsum("nk,nks->ns", w, gauss_pdf_many(rel, cov)))

    def region99(self, n: int) -> Region99:
        """A sphere around the element holding at least 99 %: it encloses every component's 99 % ellipsoid."""
        w, mu, cov = self.components(n)
        lam = np.linalg.eigvalsh(cov)[..., -1]
        radius = np.where(w > 0, np.linalg.norm(mu, axis=-1) + np.sqrt(CHI2_3_99 * np.clip(lam, 0, None)), 0).max(1)
        return Region99("sphere", np.zeros((n, 3)), np.repeat(radius[:, None], 3, axis=1),
                        np.broadcast_to(np.eye(3), (n, 3, 3)).copy())
