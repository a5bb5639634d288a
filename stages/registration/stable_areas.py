"""``stable_areas``: ICP restricted to areas known to be stable: a user box, and iterative trimming of the points whose
residuals say they lie on changed geometry (new objects bias a plain ICP)."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import Field, PositiveFloat
from scipy.spatial import cKDTree

from gdt_pipeline import StageContext, family_stage

from ._icp import ScheduleParams, icp_schedule, registration_inputs, registration_result, shifted


class StableAreasParams(ScheduleParams):
    """ICP on stable areas only: inside a box, and trimmed of points whose residuals mark them as changed."""

    method: Literal["gicp", "point_to_plane"] = "gicp"
    box: list[list[float]] | None = Field(None, description="[[xmin, ymin, zmin], [xmax, ymax, zmax]]: only recent "
                                                            "points inside it are used.")
    trim_rounds: int = Field(3, ge=0, le=20, description="Rounds of dropping points with large residuals.")
    trim_k: PositiveFloat = Field(3.0, description="Drop residuals above k robust sigmas (1.4826 MAD).")


def stable_areas(ctx: StageContext) -> dict[str, Any]:
    """ICP on the recent points in the box, trimmed round by round of those on changed geometry."""
    p = ctx.params
    inputs = registration_inputs(ctx, "stable_areas")
    tgt, src, schedule = inputs.tgt, inputs.src, inputs.schedule
    if p.box is not None:
        lo, hi = np.asarray(p.box[0]), np.asarray(p.box[1])
        src = src[np.all((src >= lo) & (src <= hi), axis=1)]
        if len(src) < 10:
            raise ValueError(f"stable_areas: only {len(src)} recent points inside the box {p.box}")
    origin = tgt.mean(axis=0)
    t_local = shifted(np.eye(4) if p.initial is None else np.asarray(p.initial), -origin)
    tree = cKDTree(tgt - origin)
    kept = src
    rmse = 0.0
    for round_ in range(p.trim_rounds + 1):
        t_local, _, rmse, _ = icp_schedule(kept, tgt, schedule, p.iterations, p.method, t_local, origin)
        if round_ == p.trim_rounds:
            break
        moved = (src - origin) @ t_local[:3, :3].T + t_local[:3, 3]
        d, _ = tree.query(moved, workers=-1)
        med = np.median(d)
        robust = 1.4826 * np.median(np.abs(d - med))
        keep = d <= med + p.trim_k * max(robust, 1e-12)
        ctx.log.info("stable_areas round %d: keeping %d of %d points (residual cut %.4g)", round_, int(keep.sum()),
                     len(src), med + p.trim_k * robust)
        kept = src[keep]
    ctx.report(stable_points=len(kept), all_points=len(src))
    return registration_result(ctx, inputs, kept, t_local, origin, rmse, f"stable_areas+{p.method}")


SPEC = family_stage("registrar", name="stable_areas", version="2.0.0", params=StableAreasParams, run=stable_areas,
                    description="ICP on stable areas only (box, and trimming of changed points).")
