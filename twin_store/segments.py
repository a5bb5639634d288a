"""A segment: the connected elements an epoch marked new (or removed), as the twin records it under ``/Segments``
and as the engine's fusion makes it (the engine re-exports it as ``gdt_pipeline.Segment``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np


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
    # a new segment that a removed part of the twin explains: that part moved (fusion): the removed segment's id,
    # the part's item key, the displacement of its centre and the rotation angle of the fitted pose
    moved_from: int | None = None
    moved_item: str | None = None
    displacement: np.ndarray | None = None
    rotation_deg: float = float("nan")
