"""Heavy tails of a scanner's residuals: a Student t fitted by maximum likelihood (ECME), chosen over the Gaussian
by BIC.

The residuals are signed distances along the surface normal. Against a mesh only that component is observed (an
offset along the surface slides along it), and the marginal of an isotropic 3-D Student t along any direction is a
1-D t with the same ν and scale, so ν and the scale fitted here are the 3-D model's. Each residual may carry a known
variance factor ``v`` (1 for ``gdt calibrate``; the sensor model's per-point variance for ``self_calibrate``), and a
uniform outlier class of half-width ``h`` may take changed points (self-calibration against a CAD that changed).

The criterion: BIC = k ln n − 2 ln L; the t (one parameter more) is chosen when it lowers BIC by more than
``BIC_MARGIN`` (10: "very strong" evidence on the Kass–Raftery scale) and ν ≤ ``MAX_DOF`` (a t with more degrees of
freedom is a Gaussian for every threshold that matters). A Gaussian sample of 10⁵ points gains 0–2 in 2 ln L from the
t's extra parameter, far below ln n + 10, so it stays Gaussian.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

BIC_MARGIN = 10.0
MAX_DOF = 100.0
DOF_BOUNDS = (0.3, 1000.0)
ROUNDS = 300


@dataclass(frozen=True)
class TailFit:
    """The t fitted to residuals beside the Gaussian, and which one the criterion chose."""

    chosen: str  # "student_t" or "gaussian"
    dof: float
    scale: float  # the t's scale factor on sqrt(v)
    location: float
    outlier_share: float
    loglik_t: float
    loglik_gaussian: float
    delta_bic: float  # BIC(Gaussian) − BIC(t): > BIC_MARGIN favours the t
    points: int
    rounds: int

    @property
    def heavy(self) -> bool:
        """Whether the t was chosen."""
        return self.chosen == "student_t"

    def record(self) -> dict[str, Any]:
        """The fit and the reason for the choice, as plain data for a profile or a report."""
        why = (f"BIC favours the Student t by {self.delta_bic:.4g} (> {BIC_MARGIN:g}) with ν = {self.dof:.3g} "
               f"(≤ {MAX_DOF:g})" if self.heavy else
               f"the Gaussian is kept: BIC(Gaussian) − BIC(t) = {self.delta_bic:.4g} (a t needs > {BIC_MARGIN:g}) "
               f"and ν = {self.dof:.3g} (a t needs ≤ {MAX_DOF:g})")
        return {"model": self.chosen, "why": why, "dof": self.dof, "scale": self.scale, "location": self.location,
                "outlier_share": self.outlier_share, "loglik_t": self.loglik_t,
                "loglik_gaussian": self.loglik_gaussian, "delta_bic": self.delta_bic, "points": self.points,
                "em_rounds": self.rounds,
                "criterion": f"BIC(Gaussian) − BIC(t) > {BIC_MARGIN:g} and ν ≤ {MAX_DOF:g}"}


def _t_logpdf(r2: np.ndarray, scale2v: np.ndarray, dof: float) -> np.ndarray:
    """log t_ν density of residuals with squared standardised value ``r2`` and variance scale ``scale2v``."""
    from scipy.special import gammaln

    return np.asarray(gammaln((dof + 1) / 2) - gammaln(dof / 2) - 0.5 * np.log(dof * np.pi * scale2v)
                      - 0.5 * (dof + 1) * np.log1p(r2 / dof))


def _mixed_loglik(log_inlier: np.ndarray, outlier: float, half_width: np.ndarray | None) -> np.ndarray:
    """Per point log[(1−π) f + π/(2h)] from log f (π = 0 without an outlier class)."""
    if half_width is None:
        return log_inlier
    return np.asarray(np.logaddexp(np.log1p(-outlier) + log_inlier, np.log(outlier) - np.log(2.0 * half_width)))


def _dof_nll(log_dof: float, r2: np.ndarray, scale2v: np.ndarray, outlier: float,
             half_width: np.ndarray | None) -> float:
    """−ln L as a function of ln ν (the other parameters held)."""
    return -float(np.sum(_mixed_loglik(_t_logpdf(r2, scale2v, float(np.exp(log_dof))), outlier, half_width)))


def fit_t(d: np.ndarray, v: np.ndarray | None = None, half_width: np.ndarray | None = None, *,
          fit_location: bool = True) -> tuple[float, float, float, float, float, int]:
    """ML Student t (ν, scale, location, outlier share) of residuals ``d`` with variance factors ``v`` and an
    optional uniform class of half-widths ``half_width``; returns them, ln L and the EM rounds."""
    from scipy import optimize

    d = np.asarray(d, dtype=np.float64)
    v = np.ones_like(d) if v is None else np.asarray(v, dtype=np.float64)
    mu = float(np.median(d)) if fit_location else 0.0
    s2 = float((1.4826 * np.median(np.abs(d - mu) / np.sqrt(v))) ** 2) or 1e-30
    dof, outlier, rounds = 5.0, 0.0 if half_width is None else 0.05, 0
    while rounds < ROUNDS:
        rounds += 1
        r2 = (d - mu) ** 2 / (s2 * v)
        log_t = _t_logpdf(r2, s2 * v, dof)
        resp = np.ones_like(d) if half_width is None else np.exp(np.log1p(-outlier) + log_t - _mixed_loglik(
            log_t, outlier, half_width))
        u = (dof + 1) / (dof + r2)  # E[latent precision | d]: small for points far in the tail
        w = resp * u / v
        mu_new = float(np.sum(w * d) / np.sum(w)) if fit_location else 0.0
        s2_new = float(np.sum(w * (d - mu_new) ** 2) / np.sum(resp))
        if half_width is not None:
            outlier = float(np.clip(1.0 - resp.mean(), 1e-4, 0.9))
        r2 = (d - mu_new) ** 2 / (s2_new * v)
        # ECME: ν maximises the observed likelihood given the other parameters
        found = optimize.minimize_scalar(_dof_nll, bounds=tuple(np.log(DOF_BOUNDS)), method="bounded",
                                         args=(r2, s2_new * v, outlier, half_width), options={"xatol": 1e-4})
        dof_new = float(np.exp(found.x))
        step = max(abs(mu_new - mu) / np.sqrt(s2), abs(np.log(s2_new / s2)), abs(np.log(dof_new / dof)))
        mu, s2, dof = mu_new, s2_new, dof_new
        if step < 1e-6:
            break
    r2 = (d - mu) ** 2 / (s2 * v)
    loglik = float(np.sum(_mixed_loglik(_t_logpdf(r2, s2 * v, dof), outlier, half_width)))
    return dof, float(np.sqrt(s2)), mu, outlier, loglik, rounds


def gaussian_loglik(d: np.ndarray, var: np.ndarray, location: float = 0.0, outlier: float = 0.0,
                    half_width: np.ndarray | None = None) -> float:
    """ln L of residuals under N(location, var) (with the uniform class when ``half_width`` is given)."""
    log_n = -0.5 * ((d - location) ** 2 / var + np.log(2 * np.pi * var))
    return float(np.sum(_mixed_loglik(log_n, outlier, half_width)))


def fit_gaussian_outliers(d: np.ndarray, v: np.ndarray, half_width: np.ndarray, rounds: int = 200
                          ) -> tuple[float, float, float]:
    """ML (location, variance scale on ``v``, outlier share) of a Gaussian with a uniform outlier class of
    half-width ``half_width`` (EM): stray points then do not make a Gaussian look heavy-tailed."""
    loc, s2, outlier = float(np.median(d)), float((1.4826 * np.median(np.abs(d - np.median(d)))) ** 2), 0.05
    s2 = max(s2, 1e-300)
    for _ in range(rounds):
        log_n = -0.5 * ((d - loc) ** 2 / (s2 * v) + np.log(2 * np.pi * s2 * v))
        resp = np.exp(np.log1p(-outlier) + log_n - _mixed_loglik(log_n, outlier, half_width))
        w = resp.sum()
        new = (float(np.sum(resp * d / v) / np.sum(resp / v)), float(np.sum(resp * (d - loc) ** 2 / v) / w),
               float(np.clip(1.0 - resp.mean(), 1e-6, 0.9)))
        converged = abs(new[1] - s2) <= 1e-6 * s2 and abs(new[2] - outlier) <= 1e-6
        loc, s2, outlier = new[0], max(new[1], 1e-300), new[2]
        if converged:
            break
    return loc, s2, outlier


def choose_tail(d: np.ndarray, *, v: np.ndarray | None = None, half_width: np.ndarray | None = None,
                gaussian: tuple[float, float, float] | None = None, fit_location: bool = True) -> TailFit:
    """The t fitted to ``d`` against the Gaussian: the ML Gaussian (mean, variance) by default, or ``gaussian``
    = (location, variance scale on ``v``, outlier share) fitted elsewhere; the t when BIC says so."""
    d = np.asarray(d, dtype=np.float64)
    v1 = np.ones_like(d) if v is None else np.asarray(v, dtype=np.float64)
    if gaussian is None and half_width is not None:  # the fair rival of a t with an outlier class
        gaussian = fit_gaussian_outliers(d, v1, half_width)
    elif gaussian is None:
        loc = float(np.mean(d)) if fit_location else 0.0
        gaussian = (loc, float(np.mean((d - loc) ** 2 / v1)), 0.0)
    loc_g, s2_g, out_g = gaussian
    ll_g = gaussian_loglik(d, s2_g * v1, loc_g, out_g, half_width)
    dof, scale, loc, outlier, ll_t, rounds = fit_t(d, v, half_width, fit_location=fit_location)
    delta = 2.0 * (ll_t - ll_g) - np.log(len(d))  # one parameter more: ν
    heavy = delta > BIC_MARGIN and dof <= MAX_DOF
    return TailFit("student_t" if heavy else "gaussian", dof, scale, loc, outlier, ll_t, ll_g, float(delta),
                   len(d), rounds)
