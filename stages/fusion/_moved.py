"""Moved parts: a part is removed at its old place and new at its new one. Where the removed segment is one part of
the twin (a CAD solid) and that part's own model, registered to a new segment (multi-start ICP, as catalogue parts
are), explains it unambiguously, the new segment records that it moved: from which removed segment, which part, the
displacement of the part's centre and the rotation angle of the fitted pose (for a symmetric part, one of its
symmetries: a box fits itself turned by 180°)."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np

from gdt_pipeline import CompositeItem, Segment, StageContext

from .parts import PartModel, fit_part, mesh_model

SAMPLES = 5000  # surface samples of a part's model for ICP
FIT_POINTS = 800  # segment points ICP uses (the fit is scored on all of them)
NEAREST = 4  # new segments tried per removed part, nearest first: each try is 48 ICP starts


def item_model(it: CompositeItem, rng: np.random.Generator) -> PartModel:
    """A twin item's mesh as a part model in twin coordinates (so that a fitted pose is the part's move)."""
    import trimesh

    mesh = trimesh.Trimesh(it.dataset.points, it.dataset.faces, process=False)
    return mesh_model(it.key, Path(it.key), hashlib.sha256(it.dataset.points.tobytes()).hexdigest(), mesh, None,
                      int(rng.integers(2**31)), SAMPLES)


def _one_item(g: Segment, keys: dict[str, CompositeItem]) -> CompositeItem | None:
    """The twin mesh item a removed segment lies on, when it lies on one only."""
    if len(g.members) != 1:
        return None
    it = keys.get(next(iter(g.members)))
    return it if it is not None and it.dataset.faces is not None else None


def moved(ctx: StageContext, items: list[CompositeItem], found: list[Segment]) -> list[Segment]:
    """The segments, with each new segment that a removed part's own model fits marked as that part moved."""
    keys = {it.key: it for it in items}
    new = [g for g in found if g.kind == "new" and not g.artefact]
    points = {g.id: np.vstack([keys[k].dataset.element_positions()[idx] for k, idx in g.members.items()])
              for g in new}
    marked: dict[int, Segment] = {}
    record = []
    by_item: dict[str, list[Segment]] = {}
    for r in (g for g in found if g.kind == "removed" and not g.artefact):
        it = _one_item(r, keys)
        if it is not None:
            by_item.setdefault(it.key, []).append(r)
    for key, removed in by_item.items():  # a part moves once: its removed pieces are one move
        model = item_model(keys[key], ctx.rng)
        best = None
        # a segment much larger than the part, or under half its size (a partial view), is not it
        sized = [g for g in new if g.id not in marked
                 and 0.4 <= np.linalg.norm(g.upper - g.lower) / model.diagonal <= 1.2]
        sized.sort(key=lambda g: float(np.linalg.norm(g.centroid - model.centre)))
        for g in sized[:NEAREST]:
            fit = fit_part(points[g.id], model, ctx.rng, max_points=FIT_POINTS)
            if fit.accepted and (best is None or fit.rms < best[1].rms):
                best = (g, fit)
        if best is None:
            continue
        g, fit = best
        r = max(removed, key=lambda x: x.size)
        shift = fit.centre - model.centre
        angle = float(np.degrees(np.arccos(np.clip((np.trace(fit.pose[:3, :3]) - 1) / 2, -1, 1))))
        marked[g.id] = dataclasses.replace(g, moved_from=r.id, moved_item=key, displacement=shift,
                                           rotation_deg=angle)
        record.append({"part": key, "removed_segments": [x.id for x in removed], "new_segment": g.id,
                       "displacement": np.round(shift, 6).tolist(), "rotation_deg": round(angle, 3),
                       "fit_rms": fit.rms, "fitness": fit.fitness})
    if record:
        ctx.report(moved=record)
        ctx.log.info("moved: %s", "; ".join(f"{m['part']} by {np.linalg.norm(m['displacement']):.4g}"
                                           for m in record))
    return [marked.get(g.id, g) if g.kind == "new" else g for g in found]
