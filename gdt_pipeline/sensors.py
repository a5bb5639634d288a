"""Sensor profiles: the noise model of a scanner, as a preset or a YAML file (``gdt calibrate`` writes one).

Model, per point at range r with incidence angle θ (between the beam and the surface normal)::

    σ_range(r, θ)   = (a0 + a1·r + a2·r²) / max(cos θ, min_cos_incidence)     along the beam
    σ_lateral(r)    = b0 + b1·r                                              across the beam, both directions

Σ = σ_range² d dᵀ + σ_lateral² (I − d dᵀ), with d the unit beam direction. A profile from ``gdt calibrate`` is
isotropic (a1 = a2 = b1 = 0, a0 = b0 = σ), which is the paper's calibrated model for the Artec Eva. With ``dof``
the noise is a Student t (heavy tails, ``gdt_pipeline.tails``) and Σ, built the same way, is its scale matrix.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .errors import GdtError
from .names import UNITS as UNITS_M
from .names import Units
from .tails import TailFit, choose_tail
from .types import Dataset


class SensorProfile(BaseModel):
    """The noise model of one scanner (see the module docstring for the formula)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    name: str
    description: str = ""
    units: Units = "m"
    range_sigma: list[float] = Field(min_length=3, max_length=3,
                                     description="a0, a1, a2 of σ_range = a0 + a1·r + a2·r² (profile units)")
    lateral_sigma: list[float] = Field(min_length=2, max_length=2, description="b0, b1 of σ_lateral = b0 + b1·r")
    min_cos_incidence: float = Field(0.2, gt=0, le=1, description="Floor of cos θ in the incidence scaling.")
    dof: float | None = Field(None, gt=0, description="Student t degrees of freedom of heavy-tailed noise (the σ "
                                                        "terms are then the t's scale); none: Gaussian.")
    calibration: dict[str, Any] | None = Field(None, description="How the profile was estimated (gdt calibrate).")

    @field_validator("range_sigma", "lateral_sigma")
    @classmethod
    def _non_negative(cls, terms: list[float]) -> list[float]:
        # a negative coefficient would be squared into a valid-looking covariance: a sign error must not pass
        bad = [f"[{i}] = {t:g}" for i, t in enumerate(terms) if t < 0]
        if bad:
            raise ValueError(f"σ coefficients must be ≥ 0; negative: {', '.join(bad)}")
        return terms

    @model_validator(mode="after")
    def _some_noise(self) -> SensorProfile:
        if not any(t > 0 for t in (*self.range_sigma, *self.lateral_sigma)):
            raise ValueError("range_sigma and lateral_sigma are all 0: a profile needs at least one σ term > 0")
        return self

    def sigmas(self, rng: np.ndarray, cos_incidence: np.ndarray | None, to_units: str) -> tuple[np.ndarray,
                                                                                                np.ndarray]:
        """σ along and across the beam, in ``to_units``, for ranges given in ``to_units``."""
        k = UNITS_M[self.units] / UNITS_M[to_units]  # profile units -> target units
        r = np.asarray(rng, dtype=np.float64) / k  # ranges in profile units
        a0, a1, a2 = self.range_sigma
        b0, b1 = self.lateral_sigma
        s_range = a0 + a1 * r + a2 * r * r
        if cos_incidence is not None:
            s_range = s_range / np.maximum(np.abs(cos_incidence), self.min_cos_incidence)
        return s_range * k, (b0 + b1 * r) * k

    def isotropic_sigma(self, to_units: str) -> float:
        """The single σ of an isotropic (calibrated) profile, in ``to_units``."""
        a0, a1, a2 = self.range_sigma
        b0, b1 = self.lateral_sigma
        if a1 or a2 or b1 or not np.isclose(a0, b0):
            raise GdtError(f"sensor profile {self.name!r} is not isotropic (range and lateral terms differ); use the "
                           f"sensor_model stage for it")
        return a0 * UNITS_M[self.units] / UNITS_M[to_units]


PRESETS: dict[str, SensorProfile] = {
    # A low-cost handheld time-of-flight camera like the Lenovo Phab 2 Pro's (paper Sec. 3): about 1 cm at 1 m,
    # growing with the square of the range, plus a few millimetres across the beam from pixel footprint and tracking.
    "tof_low_cost": SensorProfile(name="tof_low_cost", units="m", range_sigma=[0.002, 0.0, 0.008],
                                  lateral_sigma=[0.002, 0.003], min_cos_incidence=0.2,
                                  description="Low-cost handheld ToF camera (Lenovo Phab 2 Pro class)."),
    # A precise structured-light scanner like the Artec Eva (0.1 mm point accuracy at its 0.4-1 m working range).
    "structured_light": SensorProfile(name="structured_light", units="mm", range_sigma=[0.05, 0.0001, 0.0],
                                      lateral_sigma=[0.05, 0.00005], min_cos_incidence=0.3,
                                      description="Structured-light handheld scanner (Artec Eva class)."),
}


def load_profile(ref: str, base_dir: Path) -> SensorProfile:
    """A preset by name, or a profile YAML file (relative to ``base_dir``)."""
    if ref in PRESETS:
        return PRESETS[ref]
    from .workflow.marks import parse_bounded, read_text_bounded

    path = (base_dir / ref).resolve()
    if not path.exists():
        raise GdtError(f"sensor profile {ref!r}: not a preset ({', '.join(PRESETS)}) and no file {path}")
    try:
        _, data = parse_bounded(read_text_bounded(path, "sensor profile", max_bytes=1024 * 1024), str(path))
    except ValueError as exc:
        raise GdtError(f"sensor profile {ref!r}: {exc}") from None
    if not isinstance(data, dict):
        raise GdtError(f"{path}: not a valid sensor profile: a YAML mapping with name, range_sigma and lateral_sigma "
                       f"is needed")
    try:
        return SensorProfile.model_validate(data)
    except ValidationError as exc:
        what = "; ".join(f"{'.'.join(str(p) for p in e['loc']) or '(top)'}: {e['msg']}"
                         for e in exc.errors(include_url=False))
        raise GdtError(f"{path}: not a valid sensor profile: {what}") from None


def profile_problems(ref: str, base_dir: Path, *, isotropic: bool = False) -> list[str]:
    """What is wrong with a profile reference, found before a run (missing, a folder, unreadable, invalid, and for
    ``isotropic`` not isotropic); empty when it loads."""
    try:
        profile = load_profile(ref, base_dir)
        if isotropic:
            profile.isotropic_sigma("m")
    except GdtError as exc:
        return [str(exc)]
    return []


def save_profile(profile: SensorProfile, path: Path) -> Path:
    """Write a profile as YAML (readable, diffable, reusable in workflows)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    text = yaml.safe_dump(profile.model_dump(mode="json"), sort_keys=False, allow_unicode=True)
    tmp.write_text("# gdt sensor profile\n" + text, encoding="utf-8")
    tmp.replace(path)
    return path


@dataclass(frozen=True)
class Calibration:
    """Result of calibrating a scanner against a known reference: robust noise along the surface normal, and the
    heavy-tail fit that decides between a Gaussian (σ from the MAD) and a Student t (its ML scale and ν)."""

    sigma: float
    bias: float
    n_points: int
    n_used: int
    median_abs: float
    p95_abs: float
    max_abs: float
    tail: TailFit | None = None

    @property
    def profile_sigma(self) -> float:
        """The profile's σ: the t's scale when the t was chosen, else the robust Gaussian σ."""
        return self.tail.scale if self.tail is not None and self.tail.heavy else self.sigma

    @property
    def dof(self) -> float | None:
        """The profile's ν: the t's when it was chosen, else None (Gaussian)."""
        return self.tail.dof if self.tail is not None and self.tail.heavy else None

    def record(self) -> dict[str, Any]:
        """As plain data for a profile's ``calibration`` field."""
        out = {k: (float(v) if isinstance(v, float | np.floating) else v) for k, v in self.__dict__.items()
               if k != "tail"}
        return {**out, "p95_abs_over_sigma": self.p95_abs / self.sigma if self.sigma > 0 else float("nan"),
                **({} if self.tail is None else {"tail": self.tail.record()})}


def signed_distances(reference: Dataset, points: np.ndarray) -> np.ndarray:
    """Signed distance of each point to the reference mesh (positive on the side the facet normal points to)."""
    import open3d as o3d

    if reference.faces is None:
        raise GdtError(f"calibration reference {reference.name!r} must be a mesh")
    origin = reference.points.mean(axis=0)  # float32 raycasting: work near the origin
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((reference.points - origin).astype(np.float32)),
                        o3d.core.Tensor(reference.faces.astype(np.uint32)))
    q = (np.asarray(points, dtype=np.float64) - origin)
    ans = scene.compute_closest_points(o3d.core.Tensor(q.astype(np.float32)))
    closest = ans["points"].numpy().astype(np.float64)
    normals = ans["primitive_normals"].numpy().astype(np.float64)
    diff = q - closest
    return np.sign(np.einsum("ij,ij->i", diff, normals)) * np.linalg.norm(diff, axis=1)


def calibrate(reference: Dataset, scans: list[Dataset], *, max_distance: float | None = None) -> Calibration:
    """Estimate a scanner's σ from point-to-mesh distances of scans of a known object (median/MAD, robust), and
    whether a Student t fits them better (``gdt_pipeline.tails``)."""
    pts = np.concatenate([s.points for s in scans])
    d = signed_distances(reference, pts)
    used = np.isfinite(d) if max_distance is None else np.isfinite(d) & (np.abs(d) <= max_distance)
    if used.sum() < 10:
        raise GdtError(f"calibration: only {int(used.sum())} points within {max_distance} of the reference")
    du = d[used]
    med = float(np.median(du))
    sigma = 1.4826 * float(np.median(np.abs(du - med)))  # MAD of a normal sample: σ·0.6745
    return Calibration(sigma=sigma, bias=med, n_points=len(d), n_used=int(used.sum()),
                       median_abs=float(np.median(np.abs(du))), p95_abs=float(np.percentile(np.abs(du), 95)),
                       max_abs=float(np.max(np.abs(du))), tail=_tail(du))


def _tail(d: np.ndarray) -> TailFit:
    """Student t or Gaussian for calibration residuals, both with a uniform class of stray points over the
    residuals' range, so that strays (2.5 % of a simulated scan, up to 79 mm on the bunny's ear_back) never make a
    Gaussian scanner look heavy-tailed."""
    return choose_tail(d, half_width=np.full(len(d), max(float(np.max(np.abs(d))), 1e-12)))


def file_digest(path: Path) -> str:
    """sha256 of a file (for the calibration record)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
