"""Catalogue parts fitted to the segments an epoch found new, and the pieces of one part joined into one segment."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from gdt_pipeline import CompositeItem, Segment, StageContext

from ._segments import merged, nearest_within
from .parts import PartFit, PartModel, fit_part, load_part

Try = tuple[PartFit, PartModel, list[Segment]]  # a fit, the part fitted, and the segments it was fitted to


def part_problems(params: Any, base: Path) -> list[tuple[str, str]]:
    """The catalogue parts' model files, checked before a run: each present, a file, not empty."""
    out = []
    for k, p in enumerate(params.parts):
        path = Path(p.path) if Path(p.path).is_absolute() else base / p.path
        try:
            problem = (f"{path} is a directory, not a file" if path.is_dir() else
                       f"no model file {path}" if not path.is_file() else
                       f"its model file {path} is empty (0 bytes)" if path.stat().st_size == 0 else None)
        except (OSError, ValueError) as exc:  # a name too long, a NUL byte
            problem = f"not a usable file path: {exc}"
        if problem:
            out.append((f"parts.{k}.path", f"part {p.name!r}: {problem}"))
    return out


def load_parts(ctx: StageContext) -> list[PartModel]:
    """The catalogue parts of the stage's parameters, read and sampled (paths relative to the workflow)."""
    parts = []
    for k, p in enumerate(ctx.params.parts):
        path = Path(p.path) if Path(p.path).is_absolute() else Path(ctx.epoch.workflow_dir) / p.path
        if not path.is_file():
            raise ValueError(f"parts[{k}] {p.name!r}: no model file {path}")
        parts.append(load_part(p.name, path, p.max_rms, ctx.seed))
    return parts


def _tries(g: Segment, new: list[Segment], taken: set[int], parts: list[PartModel], points: dict[int, np.ndarray],
           rng: np.random.Generator) -> list[Try]:
    """Every part fitted to the seed ``g``: to the group of nearby new segments first (it must fit as one part),
    then to the segment alone if it is no larger than the part; a part stops at its first accepted fit."""
    tries = []
    for part in parts:
        group = nearest_within(g, [h for h in new if h.id not in taken], 1.2 * part.diagonal)
        for cand in ([group] if len(group) > 1 else []) + [[g]]:
            if len(cand) == 1 and np.linalg.norm(g.upper - g.lower) > 1.5 * part.diagonal:
                continue
            f = fit_part(np.vstack([points[h.id] for h in cand]), part, rng)
            tries.append((f, part, cand))
            if f.accepted:
                break
    return tries


def _joined(best: PartFit, model: PartModel, cand: list[Segment], new: list[Segment], taken: set[int],
            points: dict[int, np.ndarray]) -> tuple[PartFit, list[Segment]]:
    """The fitted segments and the other pieces the fitted part explains (new segments nearby whose elements lie on
    its surface), with the fit scored again on everything it then holds."""
    to_part = np.linalg.inv(best.pose)
    d = [model.distance(to_part, np.vstack([points[h.id] for h in cand]))]
    joined, held = list(cand), {h.id for h in cand}
    for h in new:
        if h.id in taken or h.id in held or np.linalg.norm(h.centroid - best.centre) > model.diagonal:
            continue
        dh = model.distance(to_part, points[h.id])
        if np.mean(dh <= model.max_rms) >= 0.9:
            joined.append(h)
            d.append(dh)
    if len(joined) > 1:
        d_all = np.concatenate(d)
        best = dataclasses.replace(best, rms=float(np.sqrt(np.mean(d_all**2))),
                                   fitness=float(np.mean(d_all <= model.max_rms)))
    return best, joined


def _fitted(g: Segment, new: list[Segment], taken: set[int], parts: list[PartModel], points: dict[int, np.ndarray],
            rng: np.random.Generator) -> tuple[Segment, dict[str, Any]]:
    """The seed ``g`` with the best accepted fit (joined with the pieces that fit explains; none when the fit is
    ambiguous or poor), and the record of what was tried. Marks the segments it takes in ``taken``."""
    taken.add(g.id)
    tries = _tries(g, new, taken, parts, points, rng)
    ok = [t for t in tries if t[0].accepted]
    best, joined = None, [g]
    if ok:
        best, model, cand = min(ok, key=lambda fpc: (-len(fpc[2]), fpc[0].rms))
        best, joined = _joined(best, model, cand, new, taken, points)
    taken.update(h.id for h in joined)
    seg = merged(joined, points) if len(joined) > 1 else g
    record = {"segment": g.id, "joined_sizes": [h.size for h in joined[1:]],
              "fitted": None if best is None else best.part,
              "tried": [{"part": f.part, "elements": int(sum(h.size for h in cand)), "rms": f.rms,
                         "fitness": f.fitness, "ambiguous": f.ambiguous} for f, _, cand in tries]}
    if best is None:
        return seg, record
    return dataclasses.replace(seg, part=best.part, part_pose=best.pose, part_centre=best.centre, fit_rms=best.rms,
                               fit_fitness=best.fitness), record


def fit_parts(ctx: StageContext, items: list[CompositeItem], segments: list[Segment]) -> list[Segment]:
    """Fit the catalogue parts to the new segments. Segments that one fitted part explains together (a bracket's
    plate and leg, parted where the leg hides the corner from every station) become one segment: its seed is the
    largest, joined by the nearest other new segments (artefacts too) while all fit in the part's size. A segment
    records the best accepted fit; an ambiguous or poor fit records none."""
    parts = load_parts(ctx)
    keys = {it.key: it for it in items}
    new = [g for g in segments if g.kind == "new"]
    points = {g.id: np.vstack([keys[k].dataset.element_positions()[idx] for k, idx in g.members.items()])
              for g in new}
    taken: set[int] = set()
    out, record = [], []
    for g in new:  # largest first
        if g.id in taken or g.artefact:
            continue
        seg, rec = _fitted(g, new, taken, parts, points, ctx.rng)
        out.append(seg)
        record.append(rec)
    out += [g for g in new if g.id not in taken]  # the artefacts no part took
    out += [g for g in segments if g.kind != "new"]
    out.sort(key=lambda g: (g.kind != "new", g.artefact, -g.size, g.id))
    renumber = {g.id: k for k, g in enumerate(out)}
    for r in record:
        r["segment"] = renumber[r["segment"]]
    ctx.report(parts={"models": {p.name: {"path": str(p.path), "sha256": p.sha256, "max_rms": p.max_rms}
                                 for p in parts}, "segments": record})
    return [dataclasses.replace(g, id=k) for k, g in enumerate(out)]
