"""The data that flows between stages: plain, frozen, numpy-backed dataclasses.

Every per-element quantity is an array over elements (points of a point set, facets of a mesh), never a Python
object per element. Arrays handed to these classes are made read-only so that a stage cannot change what another
stage (or the twin) still holds; a stage builds new objects with :func:`dataclasses.replace` instead.

Element convention: for a point set an element is a point; for a triangle mesh an element is a facet, and a facet
is treated as infinitely many points that share the facet's uncertainty (paper Sec. 4.2.2).
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

Role = Literal["as-designed", "as-is"]
Kind = Literal["mesh", "points"]


class ChangeState(enum.IntEnum):
    """Per-element change state; the codes are the ones stored in the twin (``gdt:changeState``)."""

    UNCHANGED = 0
    NEW = 1
    REMOVED = 2
    OUTSIDE_ROV = 3


class FusionReason(enum.IntEnum):
    """Why an element is (or is not) in the composite after an epoch's fusion; the codes are the ones stored in the
    twin (``gdt:fusionReason``, names in ``twin_store.REASON_NAMES``)."""

    BASELINE = 0
    KEPT = 1
    NEW = 2
    REMOVED = 3
    OUTSIDE_ROV = 4
    REPLACED = 5
    REPLACES = 6
    KNOWN_MORE_PRECISE = 7
    DESIGN_STAYS = 8
    KNOWN_STAYS = 9


def frozen_array(a: np.ndarray | list | tuple, dtype: type | np.dtype, ndim_shape: tuple[int | None, ...],
                 what: str) -> np.ndarray:
    """Return a read-only C-contiguous copy of ``a`` with the given dtype, checking its shape (None = any)."""
    arr = np.ascontiguousarray(np.asarray(a, dtype=dtype))
    if arr.ndim != len(ndim_shape) or any(s is not None and s != d for s, d in zip(ndim_shape, arr.shape, strict=True)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in ndim_shape) + ")"
        raise ValueError(f"{what}: expected shape {want}, got {arr.shape}")
    if arr is a or arr.base is not None:
        arr = arr.copy()
    arr.setflags(write=False)
    return arr


def _broadcast_rows(arr: np.ndarray, n: int, what: str) -> None:
    if arr.shape[0] not in (1, n):
        raise ValueError(f"{what}: {arr.shape[0]} rows for {n} elements (give 1 to broadcast, or one per element)")


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
        _broadcast_rows(self.cov, n, "gaussian covariance")
        return np.broadcast_to(self.cov, (n, 3, 3))

    def summary(self, n: int) -> np.ndarray:
        """RMS standard deviation per element, sqrt(trace(Σ)/3): a scalar for display and reports."""
        _broadcast_rows(self.cov, n, "gaussian covariance")
        return np.broadcast_to(np.sqrt(np.trace(self.cov, axis1=1, axis2=2) / 3.0), (n,))

    def take(self, idx: np.ndarray) -> GaussianUncertainty:
        """The uncertainty of the elements ``idx`` (a shared covariance stays shared)."""
        return self if self.cov.shape[0] == 1 else GaussianUncertainty(self.cov[idx])

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
        _broadcast_rows(self.half_widths, n, "box half-widths")
        var = np.broadcast_to(self.half_widths**2 / 3.0, (n, 3))
        diag = var[:, :, None] * np.eye(3)[None]
        if self.rotation is None:
            return diag
        rot = np.broadcast_to(self.rotation, (n, 3, 3))
        return rot @ diag @ np.swapaxes(rot, 1, 2)

    def summary(self, n: int) -> np.ndarray:
        """RMS standard deviation of the box per element, sqrt(Σh²/9)."""
        _broadcast_rows(self.half_widths, n, "box half-widths")
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
        _broadcast_rows(self.half_widths, n, "box half-widths")
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
        _broadcast_rows(self.weights, n, "mixture weights")
        return np.broadcast_to(np.einsum("nk,nki->ni", self.weights, self.means), (n, 3))

    def covariance(self, n: int) -> np.ndarray:
        """Covariance of each mixture about its own mean: Σ w (C + μμᵀ) − m mᵀ."""
        _broadcast_rows(self.weights, n, "mixture weights")
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
        _broadcast_rows(self.weights, n, "mixture weights")
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


@dataclass(frozen=True)
class SourceInfo:
    """Where a dataset came from: file, its sha256, the units it was written in and the scale applied on reading."""

    path: str
    sha256: str
    units: str = "m"
    scale: float = 1.0
    reader: str = ""


@dataclass(frozen=True)
class Dataset:
    """One geometry of one epoch: a point set ``points (N,3)`` or a triangle mesh ``points (V,3)`` + ``faces (F,3)``."""

    name: str
    role: Role
    points: np.ndarray
    faces: np.ndarray | None = None
    source: SourceInfo | None = None
    uncertainty: Uncertainty | None = None
    viewpoints: np.ndarray | None = None

    def __post_init__(self) -> None:
        pts = frozen_array(self.points, np.float64, (None, 3), f"dataset {self.name!r} points")
        object.__setattr__(self, "points", pts)
        if self.faces is not None:
            faces = frozen_array(self.faces, np.int64, (None, 3), f"dataset {self.name!r} faces")
            if faces.size and (faces.min() < 0 or faces.max() >= len(pts)):
                raise ValueError(f"dataset {self.name!r}: face indices outside 0..{len(pts) - 1}")
            object.__setattr__(self, "faces", faces)
        if self.viewpoints is not None:
            vps = frozen_array(self.viewpoints, np.float64, (None, 3), f"dataset {self.name!r} viewpoints")
            object.__setattr__(self, "viewpoints", vps)

    @property
    def kind(self) -> Kind:
        """"mesh" when the dataset has faces, else "points"."""
        return "mesh" if self.faces is not None else "points"

    @property
    def n_elements(self) -> int:
        """Number of elements: facets of a mesh, points of a point set."""
        return len(self.faces) if self.faces is not None else len(self.points)

    def element_positions(self) -> np.ndarray:
        """One position per element: the point itself, or the facet's centroid."""
        if self.faces is None:
            return self.points
        return self.points[self.faces].mean(axis=1)

    def facet_normals(self, idx: np.ndarray | None = None, unit: bool = False) -> np.ndarray:
        """Normals of the facets (all, or those at ``idx``) by the right-hand rule: twice the facet's area long, or
        of unit length with ``unit``."""
        if self.faces is None:
            raise ValueError(f"dataset {self.name!r} is a point set: it has no facets")
        tri = self.points[self.faces if idx is None else self.faces[idx]]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        if unit:
            normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        return normal

    def element_covariance(self) -> np.ndarray:
        """Per-element covariance ``(E,3,3)`` of the attached uncertainty (second moments of a box)."""
        if self.uncertainty is None:
            raise ValueError(f"dataset {self.name!r} has no uncertainty attached (add an uncertainty stage)")
        return self.uncertainty.covariance(self.n_elements)

    def with_uncertainty(self, uncertainty: Uncertainty) -> Dataset:
        """A copy with ``uncertainty`` attached, checked against the element count."""
        uncertainty.covariance(self.n_elements)  # raises on a row-count mismatch
        return dataclasses.replace(self, uncertainty=uncertainty)

    def transformed(self, transform: np.ndarray) -> Dataset:
        """A copy moved by a 4x4 rigid transform; covariances and box axes are rotated with it."""
        t = np.asarray(transform, dtype=np.float64)
        rot, trans = t[:3, :3], t[:3, 3]
        unc = self.uncertainty
        if isinstance(unc, GaussianUncertainty):
            unc = GaussianUncertainty(rot[None] @ unc.cov @ rot.T[None])
        elif isinstance(unc, BoxUncertainty):
            base = np.eye(3)[None] if unc.rotation is None else unc.rotation
            unc = BoxUncertainty(unc.half_widths, rot[None] @ base)
        elif isinstance(unc, MixtureUncertainty):
            unc = MixtureUncertainty(unc.weights, unc.means @ rot.T, rot @ unc.covs @ rot.T)
        vps = None if self.viewpoints is None else self.viewpoints @ rot.T + trans
        return dataclasses.replace(self, points=self.points @ rot.T + trans, uncertainty=unc, viewpoints=vps)


@dataclass(frozen=True)
class RegionOfView:
    """The space the sensors of an epoch measured: closed triangle surfaces (their union; ``parts`` gives the facet
    count of each closed part, default one part) with a vectorised ``contains``; and, once a region-of-view stage
    has looked at the reference, per reference item which elements were in view (inside and not occluded) and which
    of those the recent data matched."""

    vertices: np.ndarray
    faces: np.ndarray
    parts: tuple[int, ...] = ()
    in_view: dict[str, np.ndarray] = field(default_factory=dict)
    matched: dict[str, np.ndarray] = field(default_factory=dict)
    method: str = ""

    def __post_init__(self) -> None:
        verts = frozen_array(self.vertices, np.float64, (None, 3), "region of view vertices")
        object.__setattr__(self, "vertices", verts)
        object.__setattr__(self, "faces", frozen_array(self.faces, np.int64, (None, 3), "region of view faces"))
        parts = tuple(int(p) for p in self.parts) or (len(self.faces),)
        if sum(parts) != len(self.faces):
            raise ValueError(f"region of view: parts {parts} do not add up to its {len(self.faces)} facets")
        object.__setattr__(self, "parts", parts)

    @classmethod
    def box(cls, lower: np.ndarray | list[float], upper: np.ndarray | list[float]) -> RegionOfView:
        """An axis-aligned box region from its two corners."""
        import trimesh

        lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
        if np.any(hi <= lo):
            raise ValueError(f"region of view box: upper {hi.tolist()} must exceed lower {lo.tolist()}")
        mesh = trimesh.creation.box(extents=hi - lo)
        mesh.apply_translation((hi + lo) / 2)
        return cls(mesh.vertices, mesh.faces)

    def contains(self, points: np.ndarray, part: int | None = None) -> np.ndarray:
        """Boolean mask of the points strictly inside any of the closed parts, or inside part ``part`` only (parity
        of ray intersections each)."""
        import open3d as o3d  # imported here: open3d is heavy and only a region-of-view query needs it

        pts = o3d.core.Tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3))
        inside = np.zeros(pts.shape[0], dtype=bool)
        start = 0
        # one scene per part: overlapping closed parts would cancel each other's parity
        for k, n in enumerate(self.parts):
            if part is not None and k != part:
                start += n
                continue
            scene = o3d.t.geometry.RaycastingScene()
            faces = self.faces[start:start + n]
            used, local = np.unique(faces, return_inverse=True)
            scene.add_triangles(o3d.core.Tensor(self.vertices[used].astype(np.float32)),
                                o3d.core.Tensor(local.reshape(-1, 3).astype(np.uint32)))
            inside |= scene.compute_occupancy(pts).numpy().astype(bool)
            start += n
        return inside


@dataclass(frozen=True)
class Correspondences:
    """Candidate matches of the elements of one recent dataset in the reference.

    Each of the M candidates belongs to query element ``element[m]`` (default: candidate m is element m), compares
    the query at ``query_position[m]`` (default: the element's position; facet samples use their own) with the
    reference at ``position[m]`` whose uncertainty is that of reference element ``ref_element[m]`` of item
    ``ref_item[m]``, or row ``ref_row[m]`` of ``ref_uncertainty`` where that is ≥ 0 (a mixture of neighbours;
    default: row m for every candidate when ``ref_uncertainty`` is given). ``ref_item`` −1: no
    correspondence inside the search space. Distance stages score every candidate and keep, per element, the
    lowest score (the paper: "the candidate with the lower change score wins").
    """

    query: int
    ref_item: np.ndarray
    ref_element: np.ndarray
    position: np.ndarray
    distance: np.ndarray
    method: str = ""
    element: np.ndarray | None = None
    query_position: np.ndarray | None = None
    ref_uncertainty: Uncertainty | None = None
    n_elements: int | None = None
    ref_row: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "ref_item", frozen_array(self.ref_item, np.int64, (None,), "ref_item"))
        m = len(self.ref_item)
        if self.ref_uncertainty is not None:
            rows = np.arange(m) if self.ref_row is None else self.ref_row
            object.__setattr__(self, "ref_row", frozen_array(rows, np.int64, (m,), "ref_row"))
        object.__setattr__(self, "ref_element", frozen_array(self.ref_element, np.int64, (m,), "ref_element"))
        object.__setattr__(self, "position", frozen_array(self.position, np.float64, (m, 3), "matched position"))
        object.__setattr__(self, "distance", frozen_array(self.distance, np.float64, (m,), "distance"))
        if self.element is None:
            object.__setattr__(self, "element", np.arange(m, dtype=np.int64))
            object.__setattr__(self, "n_elements", m if self.n_elements is None else self.n_elements)
        else:
            object.__setattr__(self, "element", frozen_array(self.element, np.int64, (m,), "candidate element"))
            if self.n_elements is None:
                raise ValueError("correspondences with an element map need n_elements")
        if self.query_position is not None:
            object.__setattr__(self, "query_position",
                               frozen_array(self.query_position, np.float64, (m, 3), "query position"))

    @property
    def found(self) -> np.ndarray:
        """Mask of the candidates that are a correspondence."""
        return self.ref_item >= 0

    def element_found(self) -> np.ndarray:
        """Mask of the query elements with at least one correspondence."""
        out = np.zeros(self.n_elements, dtype=bool)
        out[self.element[self.found]] = True
        return out


@dataclass(frozen=True)
class Scores:
    """Dissimilarity per element of one recent dataset (NaN where there was no correspondence)."""

    query: int
    score: np.ndarray
    measure: str
    p_value: np.ndarray | None = None
    tolerance: float | None = None  # ε_T of a numerical integration, when the measure used one
    match: np.ndarray | None = None  # per element, the index of the winning correspondence candidate (-1: none)
    # simulate(rng, n): scores of n unchanged pairs drawn from this dataset's actual pairs' uncertainty models (the
    # null distribution a calibrated threshold needs); None when the measure cannot simulate.
    simulate: Callable[[np.random.Generator, int], np.ndarray] | None = field(default=None, compare=False,
                                                                               repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "score", frozen_array(self.score, np.float64, (None,), "score"))
        if self.p_value is not None:
            object.__setattr__(self, "p_value", frozen_array(self.p_value, np.float64, (len(self.score),), "p-value"))


@dataclass(frozen=True)
class Change:
    """Per element of one recent dataset: the score, the change mask and the change state."""

    query: int
    score: np.ndarray
    mask: np.ndarray
    state: np.ndarray
    p_value: np.ndarray | None = None
    threshold: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "score", frozen_array(self.score, np.float64, (None,), "change score"))
        n = len(self.score)
        object.__setattr__(self, "mask", frozen_array(self.mask, np.bool_, (n,), "change mask"))
        object.__setattr__(self, "state", frozen_array(self.state, np.uint8, (n,), "change state"))
        if self.p_value is not None:
            object.__setattr__(self, "p_value", frozen_array(self.p_value, np.float64, (n,), "change p-value"))


@dataclass(frozen=True)
class Registration:
    """A rigid transform from the recent data to the twin, with its quality and 6x6 covariance when known.

    The covariance is over small rotations ω about ``center`` and translations: a point x moves by ω × (x − center)
    + t. Expressing it about a centre near the data keeps georeferenced coordinates well conditioned.
    """

    transform: np.ndarray
    fitness: float = 1.0
    rmse: float = 0.0
    covariance: np.ndarray | None = None  # 6x6 over (ωx, ωy, ωz, tx, ty, tz), rotation about ``center``
    method: str = ""
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "transform", frozen_array(self.transform, np.float64, (4, 4), "transform"))
        object.__setattr__(self, "center", frozen_array(self.center, np.float64, (3,), "covariance center"))
        if self.covariance is not None:
            object.__setattr__(self, "covariance", frozen_array(self.covariance, np.float64, (6, 6), "covariance"))


@dataclass(frozen=True)
class CompositeItem:
    """One dataset held in the twin with its per-element state: what the twin stores as one prim.

    ``state`` (uint8 ChangeState codes), ``score`` (NaN = not scored), ``source_epoch`` (index of the epoch that
    supplied each element), ``visible`` (the element is part of the composite now; hidden elements stay in the
    history), ``reason`` (uint8 FusionReason codes, default baseline) and ``reason_ratio`` (the fusion rule's
    √det Σ ratio, NaN where none) are all arrays over the dataset's elements.
    """

    key: str
    dataset: Dataset
    epoch: str
    state: np.ndarray
    score: np.ndarray
    source_epoch: np.ndarray
    visible: np.ndarray
    p_value: np.ndarray | None = None
    reason: np.ndarray | None = None
    reason_ratio: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = self.dataset.n_elements
        reason = np.zeros(n, np.uint8) if self.reason is None else self.reason
        object.__setattr__(self, "reason", frozen_array(reason, np.uint8, (n,), f"{self.key}: fusion reason"))
        ratio = np.full(n, np.nan) if self.reason_ratio is None else self.reason_ratio
        object.__setattr__(self, "reason_ratio", frozen_array(ratio, np.float64, (n,), f"{self.key}: fusion ratio"))
        if self.p_value is not None:
            object.__setattr__(self, "p_value", frozen_array(self.p_value, np.float64, (n,), f"{self.key}: p-value"))
        object.__setattr__(self, "state", frozen_array(self.state, np.uint8, (n,), f"{self.key}: state"))
        object.__setattr__(self, "score", frozen_array(self.score, np.float64, (n,), f"{self.key}: score"))
        object.__setattr__(self, "source_epoch", frozen_array(self.source_epoch, np.int32, (n,), f"{self.key}: source"))
        object.__setattr__(self, "visible", frozen_array(self.visible, np.bool_, (n,), f"{self.key}: visible"))


@dataclass(frozen=True)
class Segment:
    """A connected group of the elements an epoch marked new (or removed): one added (or removed) object, so that
    "bracket added at (x, y, z)" is a query. ``members`` maps item keys to element indices; segments smaller than
    the fusion's minimum are kept and flagged ``artefact``, never dropped. ``part_centre`` is the centre of the
    catalogue part fitted to the segment, when one fits unambiguously (``centroid`` is that of what was measured)."""

    id: int
    kind: Literal["new", "removed"]
    centroid: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    mean_score: float
    size: int
    artefact: bool
    members: dict[str, np.ndarray] = field(default_factory=dict)
    # a catalogue part fitted to the segment (fusion ``parts``): its name, pose (4x4, part frame to twin), the fitted
    # model's centre, the fit's RMS point-to-surface distance and the share of elements on the model
    part: str | None = None
    part_pose: np.ndarray | None = None
    part_centre: np.ndarray | None = None
    fit_rms: float = float("nan")
    fit_fitness: float = float("nan")


@dataclass(frozen=True)
class Composite:
    """The composite 3D image after an epoch: every item the twin holds, visible or hidden, and the segments of
    what this epoch changed."""

    items: tuple[CompositeItem, ...] = ()
    segments: tuple[Segment, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "items", tuple(self.items))
        object.__setattr__(self, "segments", tuple(self.segments))
        keys = [it.key for it in self.items]
        if len(set(keys)) != len(keys):
            raise ValueError(f"composite has duplicate item keys: {sorted(k for k in set(keys) if keys.count(k) > 1)}")

    def counts(self) -> dict[str, int]:
        """Number of visible elements per change state name, over all items; "removed" counts the hidden elements
        marked removed."""
        out = {s.name.lower(): 0 for s in ChangeState}
        for it in self.items:
            codes = np.bincount(it.state[it.visible], minlength=len(ChangeState))
            for s in ChangeState:
                out[s.name.lower()] += int(codes[s])
            # removed elements leave the composite (hidden) but are what an epoch reports
            out["removed"] += int(np.sum((it.state == ChangeState.REMOVED) & ~it.visible))
        return out


@dataclass(frozen=True)
class EpochInfo:
    """What a stage may know about the epoch it runs in."""

    id: str
    index: int
    role: Role
    seed: int
    workflow_dir: Path
    units: str = "m"
