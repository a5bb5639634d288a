"""Where a scanner stood and how it sees: one station's pose, from whichever source gave it (pose file, E57 header,
workflow), and the scanner's geometry (its image's field of view, aspect and range) where the source states it."""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .arrays import frozen_array

# Where a pose may come from, highest precedence first (docs/formats.md): the simulator's or a user's pose file
# beside the scan, the scan file's own header (E57), the workflow's ``viewpoints:``.
POSE_SOURCES = ("pose_file", "file_header", "workflow")


@dataclass(frozen=True)
class ScannerGeometry:
    """How a scanner's rays spread (a pose file's ``scanner``): its ``kind`` ("pinhole" or "spherical"), horizontal
    field of view in degrees, image aspect (width / height) and the ranges it measures within (twin units). Any of
    the numbers may be unknown (None)."""

    kind: str = "pinhole"
    fov_deg: float | None = None
    aspect: float | None = None
    max_range: float | None = None
    min_range: float | None = None

    @classmethod
    def from_record(cls, record: Mapping[str, Any]) -> ScannerGeometry:
        """The geometry a pose file's ``scanner`` mapping states (other keys, such as the simulator's density and
        noise profile, are not geometry and stay in the file); a value that is not a finite number is an error."""
        numbers: dict[str, float | None] = {}
        for key in ("fov_deg", "aspect", "max_range", "min_range"):
            value = record.get(key)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int | float)
                                      or not math.isfinite(value)):
                raise ValueError(f"scanner {key!r} must be a finite number, not {value!r}")
            numbers[key] = None if value is None else float(value)
        kind = record.get("kind", "pinhole")
        if not isinstance(kind, str):
            raise ValueError(f"scanner 'kind' must be a name such as 'pinhole', not {kind!r}")
        return cls(kind=kind, **numbers)

    @property
    def pinhole_frustum(self) -> bool:
        """Whether it states a whole pinhole frustum: a pinhole with field of view, aspect and range."""
        return self.kind == "pinhole" and None not in (self.fov_deg, self.aspect, self.max_range)

    def scaled(self, scale: float) -> ScannerGeometry:
        """The geometry in other units: the ranges times ``scale``."""
        return replace(self, max_range=None if self.max_range is None else self.max_range * scale,
                       min_range=None if self.min_range is None else self.min_range * scale)


@dataclass(frozen=True)
class SensorPose:
    """A station: its position, and where known the rotation from the scanner's frame to the twin's, the point it
    looked at and its scanner's geometry (a pose file's ``scanner``).

    ``source`` is one of :data:`POSE_SOURCES`; ``origin`` names it for people (the pose file, the E57 scan)."""

    position: np.ndarray
    source: str
    origin: str = ""
    rotation: np.ndarray | None = None
    target: np.ndarray | None = None
    scanner: ScannerGeometry | None = field(default=None, compare=False, hash=False)

    def __post_init__(self) -> None:
        if self.source not in POSE_SOURCES:
            raise ValueError(f"pose source {self.source!r} is not one of {POSE_SOURCES}")
        object.__setattr__(self, "position", frozen_array(np.reshape(self.position, (1, 3)), np.float64, (1, 3),
                                                          "station position")[0])
        if self.rotation is not None:
            rot = frozen_array(np.reshape(self.rotation, (3, 3)), np.float64, (3, 3), "station rotation")
            if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
                raise ValueError(f"station rotation from {self.origin or self.source} is not a rotation matrix")
            object.__setattr__(self, "rotation", rot)
        if self.target is not None:
            tgt = frozen_array(np.reshape(self.target, (1, 3)), np.float64, (1, 3), "station target")[0]
            object.__setattr__(self, "target", tgt)

    def scaled(self, scale: float) -> SensorPose:
        """The pose in other units: positions and the scanner's ranges times ``scale``."""
        if scale == 1.0:
            return self
        return SensorPose(self.position * scale, self.source, self.origin, self.rotation,
                          None if self.target is None else self.target * scale,
                          None if self.scanner is None else self.scanner.scaled(scale))

    def transformed(self, rot: np.ndarray, trans: np.ndarray) -> SensorPose:
        """The pose moved by a rigid transform (rotation ``rot``, translation ``trans``)."""
        return SensorPose(rot @ self.position + trans, self.source, self.origin,
                          None if self.rotation is None else rot @ self.rotation,
                          None if self.target is None else rot @ self.target + trans, self.scanner)

    def record(self) -> dict[str, Any]:
        """As plain data for provenance."""
        out: dict[str, Any] = {"source": self.source, "origin": self.origin, "position": self.position.tolist()}
        if self.rotation is not None:
            out["rotation"] = self.rotation.tolist()
        if self.target is not None:
            out["target"] = self.target.tolist()
        return out
