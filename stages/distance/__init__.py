"""Distance measures (paper Sec. 4.2.1), one score per recent element against its correspondence, each a pair
function made a stage by ``gdt_pipeline.measures.distance_stage`` (pairing of correspondences, lowest score per
element, tiles, and a ``simulate(rng, n)`` on every ``Scores`` that scores n unchanged pairs drawn from the actual
uncertainty models, which the ``calibrated_threshold`` stage uses):

- ``bhattacharyya``: BD = −ln ∫√(p₁p₂) for every pair of models (closed forms where they exist, numerical
  integration with a reported tolerance ε_T otherwise; the mathematics is ``bhattacharyya_maths``);
- ``hotelling``: T² = dᵀ(Σ₁+Σ₂)⁻¹d with p-values from χ²(3), for Gaussians only (the test holds only for normals);
- ``welch_m3c2``: the M3C2-style test on equal means along the local normal, with known variances
  (t = nᵀd / √(nᵀΣ₁n + nᵀΣ₂n), two-sided p-value), as a baseline inside the pipeline;
- ``euclidean``: the plain distance, for comparison.
"""

from __future__ import annotations

from gdt_pipeline import StageSpec, hookimpl

from . import bhattacharyya, euclidean, hotelling, welch_m3c2
from .bhattacharyya import BhattacharyyaParams, bhattacharyya_gaussian
from .euclidean import EuclideanParams
from .hotelling import HotellingParams
from .welch_m3c2 import WelchParams

__all__ = ["BhattacharyyaParams", "EuclideanParams", "HotellingParams", "WelchParams", "bhattacharyya_gaussian",
           "gdt_stages"]


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in distance measures."""
    return [bhattacharyya.SPEC, hotelling.SPEC, welch_m3c2.SPEC, euclidean.SPEC]
