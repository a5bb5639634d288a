"""Positional uncertainty per element: Gaussian (full covariance), uniform box (GUM error limits) and
mixtures. Each model owns its operations: its 99 % region, sampling and density, the rows it holds and a subset
of them, repetition and concatenation (tiles), a rigid rotation, the Gaussian of equal covariance, and the arrays
the twin stores of it. ``model`` names the distribution as the twin stores it (``gdt:uncertaintyModel``)."""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from .arrays import broadcast_rows, by_pieces, covariance6, frozen_array
from .densities import gauss_pdf, gauss_pdf_many, psd_factor, t_pdf_many
from .region99 import BOX_99, CHI2_3_99, Region99, t3_radius2_99


@dataclass(frozen=True)
class GaussianUncertainty:
    """Multivariate normal positional uncertainty per element: full 3x3 covariances ``(N,3,3)`` or one ``(1,3,3)``.

    With ``dof`` (ν, one for the model) it is a Gaussian scale mixture, the multivariate Student t: an offset is
    ``L z · sqrt(ν / χ²_ν)`` with ``L Lᵀ = cov``. ``cov`` then holds the t's scale matrix Σ, not its covariance
    (ν/(ν−2)·Σ, infinite for ν ≤ 2: real scanners' residuals come out near ν = 2). ``covariance`` returns Σ, the
    Gaussian core that the measures score with (their closed forms stay exact for the core); ``sample``, ``pdf`` and
    ``region99`` are the t's, so a null simulation draws the tail (docs/uncertainty.md).
    """

    cov: np.ndarray
    model: Literal["gaussian"] = field(default="gaussian", init=False)
    dof: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "cov", frozen_array(self.cov, np.float64, (None, 3, 3), "gaussian covariance"))
        if not np.all(np.isfinite(self.cov)):
            raise ValueError("gaussian covariance has non-finite entries")
        if not np.allclose(self.cov, np.swapaxes(self.cov, 1, 2), rtol=1e-9, atol=1e-15):
            raise ValueError("gaussian covariance is not symmetric")
        if self.dof is not None:
            if not np.isfinite(self.dof) or self.dof <= 0:
                raise ValueError(f"student t degrees of freedom must be finite and > 0, got {self.dof}")
            object.__setattr__(self, "dof", float(self.dof))

    @classmethod
    def isotropic(cls, sigma: float | np.ndarray, dof: float | None = None) -> GaussianUncertainty:
        """Isotropic covariance (scale, with ``dof``) sigma² I, for one sigma or one per element."""
        s = np.atleast_1d(np.asarray(sigma, dtype=np.float64))
        return cls(cov=(s**2)[:, None, None] * np.eye(3)[None], dof=dof)

    @property
    def rows(self) -> int:
        """Rows the model holds (1: one covariance shared by every element)."""
        return int(self.cov.shape[0])

    def covariance(self, n: int) -> np.ndarray:
        """Covariances (a t's scale matrices) broadcast to ``(n,3,3)`` (a view when a single one is shared; the rows
        themselves when there is one per element, so that rows kept in a scratch file stay a ``MappedRows``)."""
        broadcast_rows(self.cov, n, "gaussian covariance")
        return self.cov if self.rows == n else np.broadcast_to(self.cov, (n, 3, 3))

    def summary(self, n: int) -> np.ndarray:
        """RMS standard deviation (a t's scale) per element, sqrt(trace(Σ)/3): a scalar for display and reports."""
        broadcast_rows(self.cov, n, "gaussian covariance")
        rms = by_pieces(self.cov, lambda rows: np.sqrt(np.trace(rows, axis1=1, axis2=2) / 3.0))
        return np.broadcast_to(rms, (n,))

    def take(self, idx: np.ndarray) -> GaussianUncertainty:
        """The uncertainty of the elements ``idx`` (a shared covariance stays shared)."""
        if self.cov.shape[0] == 1:
            return self
        cov = self.cov[idx]
        cov.setflags(write=False)
        return GaussianUncertainty.trusted(cov, self.dof)

    @classmethod
    def trusted(cls, cov: np.ndarray, dof: float | None) -> GaussianUncertainty:
        """A model of read-only (N,3,3) rows of covariances already validated (taken or merged from validated
        models): the symmetry test costs as much as a copy."""
        out = object.__new__(cls)
        object.__setattr__(out, "cov", cov)
        object.__setattr__(out, "dof", dof)
        return out

    def repeated(self, n: int) -> GaussianUncertainty:
        """The model with one row per element of ``n`` (a shared one repeated)."""
        return self if self.rows == n else GaussianUncertainty(np.repeat(self.cov, n, axis=0), dof=self.dof)

    @staticmethod
    def stacked(parts: Sequence[GaussianUncertainty]) -> GaussianUncertainty:
        """The rows of ``parts`` one after the other (they must share their ``dof``)."""
        dofs = {p.dof for p in parts}
        if len(dofs) > 1:
            raise ValueError(f"gaussian parts with different student t degrees of freedom cannot be stacked: "
                             f"{sorted(dofs, key=lambda d: -1.0 if d is None else d)}")
        return GaussianUncertainty(np.concatenate([p.cov for p in parts]), dof=parts[0].dof)

    def rotated(self, rot: np.ndarray) -> GaussianUncertainty:
        """The model turned by the rotation ``rot`` (3,3): R Σ Rᵀ."""
        return GaussianUncertainty(rot[None] @ self.cov @ rot.T[None], dof=self.dof)

    def moment_matched(self, n: int) -> GaussianUncertainty:
        """The Gaussian of equal covariance: the model itself; a t's Gaussian core (scale Σ: for ν ≤ 2 no Gaussian
        has its covariance, and the measures score every t by its core)."""
        return self if self.dof is None else GaussianUncertainty(self.cov)

    def stored(self, n: int) -> dict[str, np.ndarray]:
        """What the twin stores of the model for ``n`` elements: the packed covariances (a t's scale matrices) and,
        for a t, its degrees of freedom per element."""
        out = {"covariance": covariance6(self.covariance(n))}
        if self.dof is not None:
            out["dof"] = np.full(n, self.dof)
        return out

    def _t_weights(self, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
        """sqrt(ν/χ²_ν) per draw: the scale mixture's factor (1 for a Gaussian)."""
        if self.dof is None:
            return np.ones(shape)
        return np.asarray(np.sqrt(self.dof / rng.chisquare(self.dof, shape)))

    def sample(self, n: int, rng: np.random.Generator, k: int = 1) -> np.ndarray:
        """``k`` random offsets per element, ``(n,k,3)`` (Student t with ``dof``: one χ² per 3-D draw)."""
        factor = np.broadcast_to(psd_factor(self.cov), (n, 3, 3))
        draws = np.einsum("nij,nkj->nki", factor, rng.standard_normal((n, k, 3)))
        if self.dof is not None:
            draws = draws * self._t_weights((n, k), rng)[..., None]
        return np.asarray(draws)

    def pdf(self, offsets: np.ndarray) -> np.ndarray:
        """Density of each element's distribution at an ``(n,3)`` offset from its position."""
        d = np.asarray(offsets, dtype=np.float64)
        if self.dof is not None:
            return t_pdf_many(d[:, None, :], self.covariance(len(d)), self.dof)[:, 0]
        return gauss_pdf(d, self.covariance(len(d)))

    def pdf_many(self, offsets: np.ndarray) -> np.ndarray:
        """Densities at ``(n,S,3)`` offsets, S per element (one factorisation per element)."""
        d = np.asarray(offsets, dtype=np.float64)
        if self.dof is not None:
            return t_pdf_many(d, self.covariance(len(offsets)), self.dof)
        return gauss_pdf_many(d, self.covariance(len(offsets)))

    def region99(self, n: int) -> Region99:
        """The 99 % ellipsoid of each element (radii from the chi-square quantile with 3 degrees of freedom; for a t
        from 3·F(0.99; 3, ν), wider: the tail needs a longer reach)."""
        w, v = np.linalg.eigh(self.covariance(n))
        r2 = CHI2_3_99 if self.dof is None else t3_radius2_99(self.dof)
        return Region99("ellipsoid", np.zeros((n, 3)), np.sqrt(r2 * np.clip(w, 0.0, None)), v)


@dataclass(frozen=True)
class BoxUncertainty:
    """GUM rectangular error limits per element: uniform in a box of ``half_widths`` turned by ``rotation``.

    ``half_widths`` is ``(N,3)`` or ``(1,3)``; ``rotation`` is ``(N,3,3)``, ``(1,3,3)`` or None for axis-aligned;
    its columns are the box axes in world coordinates.
    """

    half_widths: np.ndarray
    rotation: np.ndarray | None = None
    model: Literal["box"] = field(default="box", init=False)

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

    @property
    def rows(self) -> int:
        """Rows the model holds (1: one box shared by every element)."""
        return int(max(self.half_widths.shape[0], 0 if self.rotation is None else self.rotation.shape[0]))

    def covariance(self, n: int) -> np.ndarray:
        """Covariance of the uniform box, R diag(h²/3) Rᵀ, broadcast to ``(n,3,3)``."""
        broadcast_rows(self.half_widths, n, "box half-widths")
        var = np.broadcast_to(self.half_widths**2 / 3.0, (n, 3))
        diag = var[:, :, None] * np.eye(3)[None]
        if self.rotation is None:
            return diag
        rot = np.broadcast_to(self.rotation, (n, 3, 3))
        return np.asarray(rot @ diag @ np.swapaxes(rot, 1, 2))

    def summary(self, n: int) -> np.ndarray:
        """RMS standard deviation of the box per element, sqrt(Σh²/9)."""
        broadcast_rows(self.half_widths, n, "box half-widths")
        return np.broadcast_to(np.sqrt(np.sum(self.half_widths**2, axis=1) / 9.0), (n,))

    def take(self, idx: np.ndarray) -> BoxUncertainty:
        """The uncertainty of the elements ``idx``."""
        hw = self.half_widths if self.half_widths.shape[0] == 1 else self.half_widths[idx]
        rot = None if self.rotation is None else (self.rotation if self.rotation.shape[0] == 1 else self.rotation[idx])
        return BoxUncertainty(hw, rot)

    def repeated(self, n: int) -> BoxUncertainty:
        """The model with one row per element of ``n`` (a shared one repeated)."""
        if self.rows == n:
            return self
        return BoxUncertainty(np.repeat(self.half_widths, n, axis=0),
                              None if self.rotation is None else np.repeat(self.rotation, n, axis=0))

    @staticmethod
    def stacked(parts: Sequence[BoxUncertainty]) -> BoxUncertainty:
        """The rows of ``parts`` one after the other (axis-aligned ones given the world axes when any is turned)."""
        rotated = any(p.rotation is not None for p in parts)
        rot = np.concatenate([np.broadcast_to(np.eye(3) if p.rotation is None else p.rotation, (p.rows, 3, 3))
                              for p in parts]) if rotated else None
        return BoxUncertainty(np.concatenate([p.half_widths for p in parts]), rot)

    def rotated(self, rot: np.ndarray) -> BoxUncertainty:
        """The model turned by the rotation ``rot`` (3,3): its axes R·A."""
        base = np.eye(3)[None] if self.rotation is None else self.rotation
        return BoxUncertainty(self.half_widths, rot[None] @ base)

    def moment_matched(self, n: int) -> GaussianUncertainty:
        """The Gaussian of equal covariance, per element."""
        return GaussianUncertainty(self.covariance(n))

    def stored(self, n: int) -> dict[str, np.ndarray | None]:
        """What the twin stores of the model for ``n`` elements: half-widths and box axes (None: the world's)."""
        return {"half_widths": np.broadcast_to(self.half_widths, (n, 3)),
                "rotation": None if self.rotation is None else np.broadcast_to(self.rotation, (n, 3, 3))}

    def axes(self, n: int) -> np.ndarray:
        """Box axes (columns) per element, ``(n,3,3)``."""
        return np.broadcast_to(np.eye(3) if self.rotation is None else self.rotation, (n, 3, 3))

    def sample(self, n: int, rng: np.random.Generator, k: int = 1) -> np.ndarray:
        """``k`` random offsets per element, ``(n,k,3)``, uniform in each box."""
        broadcast_rows(self.half_widths, n, "box half-widths")
        local = rng.uniform(-1.0, 1.0, (n, k, 3)) * np.broadcast_to(self.half_widths, (n, 3))[:, None, :]
        return np.asarray(np.einsum("nij,nkj->nki", self.axes(n), local))

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


from .mixture import MixtureUncertainty as MixtureUncertainty  # noqa: E402  (it builds on the Gaussian above)

Uncertainty = GaussianUncertainty | BoxUncertainty | MixtureUncertainty


def describe_model(u: Uncertainty) -> str:
    """The model's name for reports: gaussian, student_t(ν=…), box or mixture."""
    if isinstance(u, GaussianUncertainty) and u.dof is not None:
        return f"student_t(nu={u.dof:.4g})"
    return u.model


def same_model(a: Uncertainty, b: Uncertainty) -> bool:
    """Whether two models are the same (their array fields equal)."""
    return type(a) is type(b) and all(
        (x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y))
        for x, y in ((getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a) if f.init))


def concat_uncertainty(parts: Sequence[Uncertainty], counts: Sequence[int]) -> Uncertainty:
    """One model over the elements of ``parts`` one after the other (``counts[i]`` elements in part i); equal shared
    one-row models stay shared."""
    first = parts[0]
    if any(type(p) is not type(first) for p in parts):
        raise ValueError(f"tiles returned different uncertainty models: {sorted({type(p).__name__ for p in parts})}")
    if all(p.rows == 1 for p in parts) and all(same_model(p, first) for p in parts[1:]):
        return first
    full = [p.repeated(n) for p, n in zip(parts, counts, strict=True) if n]
    return type(first).stacked(full)  # type: ignore[arg-type]
