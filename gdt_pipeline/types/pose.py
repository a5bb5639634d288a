"""Where a scanner stood: one station's pose, from whichever source gave it (pose file, E57 header, workflow)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .arrays import frozen_array

# Where a pose may come from, highest precedence first (docs/formats.md): the simulator's or a user's pose file
# beside the scan, the scan file's own header (E57), the workflow's ``viewpoints:``.
POSE_SOURCES = ("pose_file", "file_header", "workflow")


@dataclass(frozen=True)
class SensorPose:
    """A station: its position, and where known the rotation from the scanner's frame to the twin's, the point it
    looked at and its scanner description (field of view, aspect, range: a pose file's ``scanner``).

    ``source`` is one of :data:`POSE_SOURCES`; ``origin`` names it for people (the pose file, the E57 scan)."""

    position: np.ndarray
    source: str
    origin: str = ""
    rotation: np.ndarray | None = None
    target: np.ndarray | None = None
    scanner: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)

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
        scanner = {k: (v * scale if k in ("max_range", "min_range") and isinstance(v, int | float) else v)
                   for k, v in self.scanner.items()}
        return SensorPose(self.position * scale, self.source, self.origin, self.rotation,
                          None if self.target is None else self.target * scale, scanner)

    def transformed(self, rot: np.ndarray, trans: np.ndarray) -> SensorPose:
        """The pose moved by a rigid transform (rotation ``rot``, translation ``trans``)."""
        return SensorPose(rot @ self.position + trans, self.source, self.origin,
                          None if self.rotation is None else rot @ self.rotation,
                          None if self.target is None else rot @ self.target + trans, dict(self.scanner))

    def record(self) -> dict[str, Any]:
        """As plain data for provenance."""
        out: dict[str, Any] = {"source": self.source, "origin": self.origin, "position": self.position.tolist()}
        if self.rotation is not None:
            out["rotation"] = self.rotation.tolist()
        if self.target is not None:
            out["target"] = self.target.tolist()
        return out
