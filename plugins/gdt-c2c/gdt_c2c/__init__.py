"""gdt-c2c: the cloud-to-cloud Euclidean distance as a gdt-pipeline distance stage (an example plugin).

The whole stage is one pair function handed to ``gdt_pipeline.measures.distance_stage``: the pairing of
correspondences, the lowest score per element and the null simulator (which ``calibrated_threshold`` needs) come
from the public measures API, and the distance itself is ``measures.euclidean``, the one the built-in ``euclidean``
stage uses.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat

from gdt_pipeline import StageSpec, hookimpl
from gdt_pipeline.measures import MeasureResult, PairGroup, distance_stage, euclidean

__version__ = "0.2.0"


class C2CParams(BaseModel):
    """Parameters of the C2C distance."""

    model_config = ConfigDict(extra="forbid")
    scale: PositiveFloat = Field(1.0, description="Multiply distances by this (e.g. 1000 for mm in a metre twin).")


def c2c(group: PairGroup, rng: np.random.Generator, params: C2CParams) -> MeasureResult:
    """Euclidean distance of each candidate pair, scaled; the closest candidate of an element wins."""
    return euclidean(group, rng, params.scale)


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The stages of this plugin."""
    return [distance_stage(name="c2c", measure=c2c, params=C2CParams, version=__version__,
                           description="Euclidean cloud-to-cloud distance (ignores uncertainty; its null "
                                       "simulator uses it, for calibrated_threshold).")]
