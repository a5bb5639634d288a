"""Correspondences. Here ``nearest``: each recent element (a point, or a facet's centroid) is matched to the closest
visible reference element (a point through a KD-tree, or the closest point on a facet through Open3D raycasting).
The uncertainty-directed cases of the paper come with the correspondence issue."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, PositiveFloat

from gdt_pipeline import Correspondences, StageContext, StageSpec, hookimpl
from gdt_pipeline.geometry import ReferenceIndex


class NearestParams(BaseModel):
    """Parameters of the nearest-element correspondence search."""

    model_config = ConfigDict(extra="forbid")
    max_distance: PositiveFloat | None = Field(
        None, description="Search radius in twin units; elements with nothing closer get no correspondence "
                          "(they become new). Default: unlimited.")


def _nearest(ctx: StageContext) -> dict[str, Any]:
    index = ReferenceIndex(ctx["reference"])
    out = []
    recent = ctx["recent"]
    with ctx.progress.task("nearest reference elements", total=len(recent)) as advance:
        for qi, ds in enumerate(recent):
            res = index.nearest(ds.element_positions(), ctx.params.max_distance)
            out.append(Correspondences(query=qi, ref_item=res.item, ref_element=res.element, position=res.position,
                                       distance=res.distance, method="nearest"))
            ctx.log.info("%s: %d of %d elements matched", ds.name, int((res.item >= 0).sum()), ds.n_elements)
            advance()
    return {"correspondences": out}


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in correspondence estimators."""
    return [StageSpec(name="nearest", family="correspondence", version="1.0.0", params=NearestParams, run=_nearest,
                      requires=("recent", "reference"), provides=("correspondences",),
                      description="Closest visible reference point or facet (Euclidean).")]
