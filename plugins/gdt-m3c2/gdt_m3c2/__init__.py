"""gdt-m3c2: py4dgeo's M3C2 (Lague et al. 2013) inside the pipeline, as the distance stage ``m3c2``.

Per recent dataset, M3C2 measures along the local normal from the reference (epoch 1: the composite so far, its
visible points and its visible facets sampled, ``gdt_pipeline.measures.reference_cloud``) to the recent data
(epoch 2: its points, or its facets sampled), at the recent elements' positions as core points. The score is the
significance of that distance: |distance| / LoD, with py4dgeo's level of detection
LoD = 1.96·(√(σ₁²/n₁ + σ₂²/n₂) + registration_error), so an element is changed above 1. The p-value is the
two-sided normal one M3C2's LoD stands for, p = 2Φ(−1.96·score): the LoD is the 95 % bound of a normal model of the
difference of the two cylinder means, so ``significance`` with α = 0.05 makes M3C2's own decision (the registration
error is added to the standard error, as M3C2 does, which makes the p-value conservative). NaN where M3C2 gives
none (too few points in a cylinder): no counterpart, which a threshold counts as changed.

Measured on py4dgeo 1.2.0: a core point with fewer than three reference points within the largest normal radius
gets no normal, and py4dgeo leaves that row of its normals uninitialised, so the distance it reports there is
whatever the memory held (it changes from run to run). The stage gives NaN there, as for any point M3C2 cannot
measure.
"""

from __future__ import annotations

import contextlib
import io
import logging
from collections.abc import Iterator
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, NonNegativeFloat, PositiveFloat
from scipy.spatial import cKDTree
from scipy.special import ndtr

from gdt_pipeline import Scores, StageContext, StageSpec, hookimpl
from gdt_pipeline.geometry import sample_surface
from gdt_pipeline.measures import reference_cloud

__version__ = "0.1.0"
Z95 = 1.96  # py4dgeo's two-sided 95 % factor in the LoD


class M3C2Params(BaseModel):
    """py4dgeo's M3C2 parameters, in the twin's units."""

    model_config = ConfigDict(extra="forbid")
    cyl_radius: PositiveFloat = Field(description="Radius of the cylinder around the normal through a core point "
                                                  "whose points of each epoch are averaged (py4dgeo cyl_radius).")
    normal_radii: list[PositiveFloat] = Field(
        min_length=1, description="Radii of the neighbourhoods the normal is fitted in, on the reference cloud; with "
                                  "several, py4dgeo keeps the most planar fit (py4dgeo normal_radii).")
    max_distance: PositiveFloat = Field(description="Half length of the cylinder along the normal: points farther "
                                                    "from the core point are not used (py4dgeo max_distance).")
    registration_error: NonNegativeFloat = Field(0.0, description="Registration error added to the LoD's spread "
                                                                  "(py4dgeo registration_error).")
    mesh_spacing: PositiveFloat | None = Field(None, description="Sample spacing on mesh facets (reference or "
                                                                 "recent); default a third of cyl_radius.")


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """py4dgeo logs every KD-tree it builds and may print: keep the run's own output readable."""
    logger = logging.getLogger("py4dgeo")
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            yield
    finally:
        logger.setLevel(level)


def _cloud(points: np.ndarray) -> np.ndarray:
    # py4dgeo takes writeable C-contiguous float64 only; the pipeline's arrays are read-only
    return np.array(points, dtype=np.float64, order="C", copy=True)


def m3c2_distances(reference: np.ndarray, recent: np.ndarray, core: np.ndarray, params: M3C2Params
                   ) -> tuple[np.ndarray, np.ndarray]:
    """py4dgeo's M3C2 distance (recent minus reference, along the normal) and LoD at each core point."""
    import py4dgeo  # heavy; only when the stage runs

    with _quiet():
        algo = py4dgeo.M3C2(epochs=(py4dgeo.Epoch(_cloud(reference)), py4dgeo.Epoch(_cloud(recent))),
                            corepoints=_cloud(core), cyl_radius=float(params.cyl_radius),
                            normal_radii=[float(r) for r in params.normal_radii],
                            max_distance=float(params.max_distance),
                            registration_error=float(params.registration_error))
        distance, uncertainty = algo.run()
    distance = np.asarray(distance, dtype=np.float64)
    lod = np.asarray(uncertainty["lodetection"], dtype=np.float64)
    no_normal = without_normal(reference, core, max(params.normal_radii))
    distance[no_normal], lod[no_normal] = np.nan, np.nan
    return distance, lod


def without_normal(reference: np.ndarray, core: np.ndarray, radius: float) -> np.ndarray:
    """Core points with fewer than three reference points within ``radius``: no plane, so no M3C2 normal."""
    return cKDTree(reference).query_ball_point(core, radius, return_length=True) < 3


def significance(distance: np.ndarray, lod: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Score |distance| / LoD (changed above 1) and the two-sided p-value 2Φ(−1.96·score) it stands for."""
    with np.errstate(divide="ignore", invalid="ignore"):
        score = np.abs(distance) / lod
    return score, 2.0 * ndtr(-Z95 * score)


def _m3c2(ctx: StageContext) -> dict[str, Any]:
    p = ctx.params
    spacing = p.mesh_spacing or p.cyl_radius / 3.0
    reference = reference_cloud(ctx["reference"], spacing, ctx.rng)
    out, lods = [], []
    with ctx.progress.task("m3c2 distances", total=len(ctx["recent"])) as advance:
        for q, ds in enumerate(ctx["recent"]):
            core = ds.element_positions()
            if len(reference) == 0 or ds.n_elements == 0:
                distance, lod = np.full(ds.n_elements, np.nan), np.full(ds.n_elements, np.nan)
            else:
                distance, lod = m3c2_distances(reference, sample_surface(ds, spacing, ctx.rng), core, p)
            score, p_value = significance(distance, lod)
            out.append(Scores(query=q, score=score, measure="m3c2", p_value=p_value))
            lods.append(lod)
            advance()
    every = np.concatenate(lods) if lods else np.zeros(0)
    ctx.report(reference_points=len(reference), no_distance=int(np.isnan(every).sum()),
               median_lod=float(np.nanmedian(every)) if np.isfinite(every).any() else None)
    return {"scores": out}


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The stages of this plugin."""
    return [StageSpec(name="m3c2", family="distance", version=__version__, params=M3C2Params, run=_m3c2,
                      requires=("recent", "reference"), provides=("scores",),
                      description="py4dgeo's M3C2 from the composite to the recent data; score |distance| / LoD, "
                                  "p-values from the LoD's normal model.")]
