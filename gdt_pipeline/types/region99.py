"""The 99 % probability region of a per-element distribution: an ellipsoid, a box or a sphere of offsets."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

CHI2_3_99 = 11.344866730144373  # chi-square quantile, 3 degrees of freedom, p = 0.99 (scipy.stats.chi2.ppf)
BOX_99 = 0.99 ** (1.0 / 3.0)  # a centred box scaled by this holds 99 % of a uniform box's mass


def t3_radius2_99(dof: float) -> float:
    """Squared radius, in scale units, of the 3-D Student t's 99 % ellipsoid: its squared Mahalanobis distance over 3
    follows F(3, ν), so 3·F⁻¹(0.99; 3, ν) (χ²₃(0.99) = 11.34 as ν → ∞; 50.1 at ν = 4, 297 at ν = 2)."""
    from scipy.stats import f  # type: ignore[import-untyped]  # here: scipy.stats costs a quarter of a second to import

    return float(3.0 * f.ppf(0.99, 3.0, dof))


def reach_factor(model: object) -> float:
    """How much farther than a Gaussian's of the same scale a model's 99 % region reaches: 1 for every model but a
    Student t, whose tail puts its 99 % ellipsoid √(3·F⁻¹(0.99; 3, ν) / χ²₃(0.99)) times as far out (2.8 at
    ν = 2.9, the bunny scanner's). Correspondence searches scale their reach by it, so that the tail a calibration
    found is scored rather than left without a partner."""
    dof = getattr(model, "dof", None)
    return 1.0 if dof is None else float(np.sqrt(t3_radius2_99(float(dof)) / CHI2_3_99))


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
            return np.asarray(np.linalg.norm(d, axis=-1) <= self.half_axes[..., 0])
        local = np.einsum("nji,nj->ni", self.axes, d)
        scaled = np.divide(local, self.half_axes, out=np.full_like(local, np.inf), where=self.half_axes > 0)
        scaled[(self.half_axes == 0) & (np.abs(local) < 1e-15)] = 0.0
        if self.kind == "box":
            return np.asarray(np.all(np.abs(scaled) <= 1.0, axis=-1))
        return np.asarray(np.einsum("ni,ni->n", scaled, scaled) <= 1.0)

    def bounding_radius(self) -> np.ndarray:
        """Radius of a sphere around the element position that holds the whole region (for KD-tree searches)."""
        c = np.linalg.norm(self.center, axis=-1)
        if self.kind == "sphere":
            return np.asarray(c + self.half_axes[..., 0])
        if self.kind == "box":
            return np.asarray(c + np.linalg.norm(self.half_axes, axis=-1))
        return np.asarray(c + self.half_axes.max(axis=-1))
