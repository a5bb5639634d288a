"""Densities and factors behind the uncertainty models: Gaussian and Student t densities for many samples per
element, and a factor of a positive semi-definite covariance."""
from __future__ import annotations

import math

import numpy as np


def psd_factor(cov: np.ndarray) -> np.ndarray:
    """A factor L with L Lᵀ = Σ for symmetric positive semi-definite Σ (eigen-based: works when Σ is singular)."""
    w, v = np.linalg.eigh(cov)
    return np.asarray(v * np.sqrt(np.clip(w, 0.0, None))[..., None, :])


def gauss_pdf_many(d: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """N(d; 0, C) for ``d (..., S, 3)`` and ``cov (..., 3, 3)``: one factorisation per covariance, S samples each."""
    chol = np.linalg.cholesky(cov)
    inv = np.linalg.inv(chol)
    y = np.einsum("...ij,...sj->...si", inv, d)
    logdet = 2.0 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(axis=-1)
    exponent = -0.5 * np.einsum("...si,...si->...s", y, y) - 0.5 * logdet[..., None] - 1.5 * np.log(2 * np.pi)
    return np.asarray(np.exp(exponent))


def gauss_pdf(d: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """N(d; 0, C) for ``d (..., 3)`` and ``cov (..., 3, 3)``, one sample per covariance."""
    chol = np.linalg.cholesky(cov)
    y = np.linalg.solve(chol, d[..., None])[..., 0]
    logdet = 2.0 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(axis=-1)
    return np.asarray(np.exp(-0.5 * np.einsum("...i,...i->...", y, y) - 0.5 * logdet - 1.5 * np.log(2 * np.pi)))


def t_pdf_many(d: np.ndarray, scale: np.ndarray, dof: float) -> np.ndarray:
    """The 3-D Student t density t_ν(d; 0, Σ) for ``d (n,S,3)`` and scale matrices ``scale (n,3,3)``."""
    chol = np.linalg.cholesky(scale)
    y = np.einsum("nij,nsj->nsi", np.linalg.inv(chol), d)
    logdet = 2.0 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(axis=-1)
    m2 = np.einsum("nsi,nsi->ns", y, y)
    const = math.lgamma((dof + 3) / 2) - math.lgamma(dof / 2) - 1.5 * math.log(dof * math.pi)
    return np.asarray(np.exp(const - 0.5 * logdet[:, None] - 0.5 * (dof + 3) * np.log1p(m2 / dof)))
