"""gdt-c2c: the cloud-to-cloud Euclidean distance as a gdt-pipeline distance stage (an example plugin)."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat

from gdt_pipeline import Scores, StageContext, StageSpec, hookimpl

__version__ = "0.1.0"


class C2CParams(BaseModel):
    """Parameters of the C2C distance."""

    model_config = ConfigDict(extra="forbid")
    scale: PositiveFloat = Field(1.0, description="Multiply distances by this (e.g. 1000 for mm in a metre twin).")


def c2c(ctx: StageContext) -> dict[str, Any]:
    """Euclidean distance of each recent element to its nearest corresponding candidate (NaN when none)."""
    recent = ctx["recent"]
    out = []
    for corr in ctx["correspondences"]:
        ds = recent[corr.query]
        qpos = corr.query_position if corr.query_position is not None else ds.element_positions()[corr.element]
        d = np.where(corr.found, np.linalg.norm(qpos - corr.position, axis=1) * ctx.params.scale, np.nan)
        score = np.full(ds.n_elements, np.nan)
        np.fmin.at(score, corr.element, d)  # several candidates per element: the closest one counts
        out.append(Scores(query=corr.query, score=score, measure="c2c"))
    return {"scores": out}


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The stages of this plugin."""
    return [StageSpec(name="c2c", family="distance", version=__version__, params=C2CParams, run=c2c,
                      requires=("recent", "correspondences"), provides=("scores",),
                      description="Euclidean cloud-to-cloud distance (ignores uncertainty).")]
