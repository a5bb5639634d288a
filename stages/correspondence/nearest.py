"""``nearest``: the plain baseline correspondence, each element (a point, or a facet's centroid) matched to the
closest visible reference element."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat

from gdt_pipeline import Correspondences, StageContext, family_stage
from gdt_pipeline.geometry import ReferenceIndex
from gdt_pipeline.geometry.extent import check_scales


class NearestParams(BaseModel):
    """Parameters of the nearest-element correspondence search."""

    model_config = ConfigDict(extra="forbid")
    max_distance: PositiveFloat | None = Field(
        None, description="Search radius in twin units; elements with nothing closer get no correspondence "
                          "(they become new). Default: unlimited.")


def _nearest(ctx: StageContext) -> dict[str, Any]:
    check_scales(ctx["recent"], ctx["reference"], "nearest")
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


def _nearest_reach(params: NearestParams, slots: Mapping[str, Any]) -> float:
    """The search radius; without one, the whole scene's diagonal (every tile then sees everything)."""
    if params.max_distance is not None:
        return float(params.max_distance)
    pts = [ds.points for ds in slots["recent"]] + [it.dataset.points for it in slots["reference"].items]
    pts = [p for p in pts if len(p)]
    if not pts:
        return 0.0
    return float(np.linalg.norm(np.max([p.max(axis=0) for p in pts], axis=0) - np.min([p.min(axis=0) for p in pts],
                                                                                          axis=0)))


SPEC = family_stage("correspondence", name="nearest", version="1.0.0", params=NearestParams, run=_nearest,
                    tiling="tile", reach=_nearest_reach,
                    description="Closest visible reference point or facet (Euclidean baseline).")
