"""``euclidean``: the plain distance to the corresponding position, for comparison."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat

from gdt_pipeline.measures import MeasureResult, PairGroup, distance_stage, euclidean


class EuclideanParams(BaseModel):
    """Plain Euclidean distance."""

    model_config = ConfigDict(extra="forbid")
    scale: PositiveFloat = Field(1.0, description="Multiply distances by this (e.g. 1000 for mm in a metre twin).")


def euclidean_pairs(g: PairGroup, rng: np.random.Generator, params: EuclideanParams) -> MeasureResult:
    """The Euclidean distance of each pair, scaled."""
    return euclidean(g, rng, params.scale)


SPEC = distance_stage(name="euclidean", measure=euclidean_pairs, params=EuclideanParams, version="1.2.0",
                      description="Plain Euclidean distance to the corresponding position.")
