"""Fusion: the composite 3D image after each epoch.

- ``keep_unchanged`` (also under the name ``keep_reference``): the known data stays, the changed elements of the new
  data come in, and the unchanged new elements are kept in the twin's history but hidden (the known data already
  images them);
- ``most_reliable``: as keep_unchanged, except where the new data images unchanged, measured (as-is) geometry inside
  its region of view with a smaller uncertainty (√det Σ, the volume of its error ellipsoid) than the known data:
  there the new data replaces the old (the paper's E2 replacing E1). Design (CAD) geometry stays the design unless
  ``replace_design``;
- ``replace_in_view``: the newest data always replaces what it images inside the region of view.

Replaced elements are hidden, not dropped; the numbers of the rule go into the epoch's report.

Change states are per epoch: elements carried over from an earlier epoch go back to "unchanged" unless this epoch
changes them; the first epoch is the baseline, so its elements are "unchanged" too. Removal needs the region of
view: with a region-of-view stage in the chain, a reference element in view that no recent data matches is
"removed" and leaves the composite (it stays in the history), and one outside the region of view is marked so and
kept as it was (never removed)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from gdt_pipeline import (
    ChangeState,
    Composite,
    CompositeItem,
    Dataset,
    FusionReason,
    Segment,
    StageContext,
    StageSpec,
    hookimpl,
)


class PartParams(BaseModel):
    """A catalogue part to recognise among the new segments."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field(description="The part's name (a part number), recorded on the segments it fits.")
    path: str = Field(description="Its CAD model (any mesh format trimesh reads; relative to the workflow file), "
                                  "in the part's own frame and the workflow's units.")
    max_rms: float | None = Field(None, gt=0, description="Largest RMS point-to-surface distance of a fit it "
                                                          "accepts (default: 2 % of the part's diagonal).")


class SegmentParams(BaseModel):
    """How changed elements are grouped into objects (every fusion)."""

    model_config = ConfigDict(extra="forbid")
    parts: list[PartParams] = Field(default_factory=list, description="Catalogue parts fitted to every new segment "
                                                                      "(multi-start ICP): the segment records the "
                                                                      "part whose model fits, its pose and centre.")
    segment_radius: float | None = Field(None, gt=0, description="Elements closer than this are one object "
                                                                 "(default: 3 × their typical spacing, at least "
                                                                 "1.5σ of their largest axis).")
    min_segment_size: int = Field(10, ge=1, description="Segments with fewer elements are reported as artefacts.")


class KeepUnchangedParams(SegmentParams):
    """``keep_unchanged``: only the segmentation parameters."""


class MostReliableParams(SegmentParams):
    """When new data replaces the known data."""

    replace_design: bool = Field(False, description="Let precise measurements replace as-designed (CAD) elements "
                                                    "too (default: the design stays where it is confirmed).")
    ratio: float = Field(1.0, gt=0, le=1, description="New data must have √det Σ below this share of the known "
                                                      "data's.")


class ReplaceInViewParams(SegmentParams):
    """``replace_in_view``: only the segmentation parameters."""


def _check(available: frozenset[str]) -> str | None:
    if "reference" in available and "change" not in available:
        return "fusion 'keep_unchanged' needs slot 'change' once a reference exists (add distance and threshold stages)"
    return None


def _keep_unchanged(ctx: StageContext) -> dict[str, Any]:
    return _fuse(ctx, None)


def _most_reliable(ctx: StageContext) -> dict[str, Any]:
    return _fuse(ctx, "most_reliable")


def _replace_in_view(ctx: StageContext) -> dict[str, Any]:
    return _fuse(ctx, "replace_in_view")


def _spread(ds: Dataset, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """√det Σ (the volume of the error ellipsoid) and the largest-axis σ of the given elements, from one covariance
    evaluation; inf and 0 where the dataset carries no uncertainty (it can never be the more precise)."""
    if ds.uncertainty is None:
        return np.full(len(idx), np.inf), np.zeros(len(idx))
    cov = ds.element_covariance()[idx]
    return np.sqrt(np.maximum(np.linalg.det(cov), 0.0)), np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, -1], 0.0))


@dataclasses.dataclass
class _Decision:
    """What the replacement rule decided: per known item the replaced elements and their ratios, per recent
    dataset the taking elements and, for every unchanged recent element, its reason code and ratio."""

    replaced: dict[int, np.ndarray]
    replaced_ratio: dict[int, np.ndarray]
    taking: dict[int, np.ndarray]
    reason: dict[int, np.ndarray]
    ratio: dict[int, np.ndarray]


def _replacements(ctx: StageContext, items: list[CompositeItem], policy: str) -> _Decision:
    """Which known elements the unchanged recent elements replace, and why each unchanged recent element does or
    does not take their place."""
    rov = ctx.get("rov")
    if rov is None:
        raise ValueError(f"fusion {policy!r} needs a region-of-view stage before it (sensor_frustum or manual_box): "
                         f"new data replaces old only where its region of view encloses the old")
    changes = {c.query: c for c in ctx.get("change") or []}
    out = _Decision({i: np.zeros(it.dataset.n_elements, bool) for i, it in enumerate(items)},
                    {i: np.full(it.dataset.n_elements, np.nan) for i, it in enumerate(items)}, {}, {}, {})
    keep_design = policy == "most_reliable" and not ctx.params.replace_design
    pos, owner, elem, design = [], [], [], []
    for i, it in enumerate(items):
        view = rov.in_view.get(it.key)
        if view is None:
            continue
        idx = np.flatnonzero(view & it.visible)
        pos.append(it.dataset.element_positions()[idx])
        owner.append(np.full(idx.size, i))
        elem.append(idx)
        design.append(np.full(idx.size, it.dataset.role == "as-designed"))
    if not sum(len(p) for p in pos):
        return out
    all_pos, all_design = np.vstack(pos), np.concatenate(design)
    # the design stays under most_reliable: only measured known elements can be replaced
    sel_known = ~all_design if keep_design else np.ones(len(all_pos), bool)
    pos_a, owner_a, elem_a = all_pos[sel_known], np.concatenate(owner)[sel_known], np.concatenate(elem)[sel_known]
    design_tree = cKDTree(all_pos[all_design]) if keep_design and all_design.any() else None
    design_gap = (float(np.median(design_tree.query(design_tree.data, k=2)[0][:, 1]))
                  if design_tree is not None and design_tree.n > 1 else 0.0)
    tree = cKDTree(pos_a) if len(pos_a) else None
    ref_gap = float(np.median(tree.query(pos_a, k=2)[0][:, 1])) if len(pos_a) > 1 else 0.0
    own = np.zeros(len(pos_a))
    vol_known = np.full(len(pos_a), np.inf)
    for i in np.unique(owner_a):
        sel = owner_a == i
        vol_known[sel], sigma = _spread(items[i].dataset, elem_a[sel])
        own[sel] = 3.0 * sigma
    takers: list[np.ndarray] = []
    taker_vol: list[np.ndarray] = []
    for qi, ds in enumerate(ctx["recent"]):
        ch = changes.get(qi)
        if ch is None:
            continue
        reason = np.full(ds.n_elements, FusionReason.KNOWN_STAYS, np.uint8)
        ratio = np.full(ds.n_elements, np.nan)
        out.reason[qi], out.ratio[qi] = reason, ratio
        cand = np.flatnonzero(ch.state == ChangeState.UNCHANGED)
        if not cand.size:
            continue
        rpos = ds.element_positions()[cand]
        v_new, sigma = _spread(ds, cand)
        spacing = 3.0 * sigma
        if design_tree is not None:
            d_design, _ = design_tree.query(rpos)
            reason[cand[d_design <= np.maximum(spacing, 2.0 * design_gap)]] = FusionReason.DESIGN_STAYS
        if tree is None:
            continue
        d, j = tree.query(rpos)
        # an unchanged recent element images its nearest in-view known element when it lies within 3σ of either's
        # largest axis or twice the known data's spacing (a sparse noisy reference is farther away than the
        # precise σ)
        near = d <= np.maximum(np.maximum(spacing, own[j]), 2.0 * ref_gap)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = v_new / vol_known[j]
        take = near.copy()
        if policy == "most_reliable":
            take &= v_new < ctx.params.ratio * vol_known[j]
            reason[cand[near & ~take]] = FusionReason.KNOWN_MORE_PRECISE
        reason[cand[take]] = FusionReason.REPLACES
        ratio[cand[near]] = np.where(np.isfinite(r[near]), r[near], np.nan)
        mask = np.zeros(ds.n_elements, bool)
        mask[cand[take]] = True
        out.taking[qi] = mask
        takers.append(rpos[take])
        taker_vol.append(v_new[take])
    if not takers or not sum(len(t) for t in takers):
        return out
    # every known element the taking data images goes, not only the nearest of each: a known element within 3σ of
    # its own largest axis (or twice the typical gap) of taking data is replaced
    dist, k = cKDTree(np.vstack(takers)).query(pos_a)
    hit = dist <= np.maximum(own, 2.0 * ref_gap)
    with np.errstate(invalid="ignore", divide="ignore"):
        r_known = np.concatenate(taker_vol)[k] / vol_known
    for i in np.unique(owner_a[hit]):
        sel = hit & (owner_a == i)
        out.replaced[i][elem_a[sel]] = True
        out.replaced_ratio[i][elem_a[sel]] = np.where(np.isfinite(r_known[sel]), r_known[sel], np.nan)
    return out


def _segments(items: list[CompositeItem], masks: dict[int, np.ndarray], kind: str, params: SegmentParams,
              start_id: int) -> list[Segment]:
    """Connected groups (radius graph) of the masked elements over all items."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pos, owner, elem, score, sig = [], [], [], [], []
    for i, mask in masks.items():
        idx = np.flatnonzero(mask)
        if not idx.size:
            continue
        ds = items[i].dataset
        pos.append(ds.element_positions()[idx])
        owner.append(np.full(idx.size, i))
        elem.append(idx)
        score.append(items[i].score[idx])
        sig.append(_spread(ds, idx)[1])
    if not pos:
        return []
    pos_a, owner_a, elem_a = np.vstack(pos), np.concatenate(owner), np.concatenate(elem)
    score_a, sig_a = np.concatenate(score), np.concatenate(sig)
    tree = cKDTree(pos_a)
    radius = params.segment_radius
    if radius is None:
        gap = tree.query(pos_a, k=2)[0][:, 1] if len(pos_a) > 1 else np.zeros(1)
        radius = max(3.0 * float(np.median(gap)), 1.5 * float(np.median(sig_a)), 1e-9)
    pairs = tree.query_pairs(radius, output_type="ndarray")
    n = len(pos_a)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else \
        coo_matrix((n, n))
    _, label = connected_components(graph, directed=False)
    order = np.argsort(label, kind="stable")
    bounds = np.flatnonzero(np.diff(label[order])) + 1
    out = []
    groups = sorted(np.split(order, bounds), key=lambda g: (-len(g), int(g.min())))  # largest first, stable ids
    for k, g in enumerate(groups):
        members = {items[i].key: np.sort(elem_a[g][owner_a[g] == i]) for i in np.unique(owner_a[g])}
        finite = score_a[g][np.isfinite(score_a[g])]
        out.append(Segment(id=start_id + k, kind=kind, centroid=pos_a[g].mean(axis=0), lower=pos_a[g].min(axis=0),
                           upper=pos_a[g].max(axis=0), mean_score=float(finite.mean()) if finite.size else float("nan"),
                           size=len(g), artefact=len(g) < params.min_segment_size, members=members))
    return out


def _merged(parts: list[Segment], points: dict[int, np.ndarray]) -> Segment:
    """One segment of several (their members, positions and scores pooled) under the first one's id."""
    members: dict[str, list[np.ndarray]] = {}
    for g in parts:
        for key, idx in g.members.items():
            members.setdefault(key, []).append(idx)
    pts = np.vstack([points[g.id] for g in parts])
    sizes = np.array([g.size for g in parts], dtype=np.float64)
    scores = np.array([g.mean_score for g in parts])
    ok = np.isfinite(scores)
    mean_score = float(np.average(scores[ok], weights=sizes[ok])) if ok.any() else float("nan")
    return dataclasses.replace(parts[0], centroid=pts.mean(axis=0), lower=pts.min(axis=0), upper=pts.max(axis=0),
                               mean_score=mean_score, size=int(sizes.sum()), artefact=False,
                               members={k: np.sort(np.concatenate(v)) for k, v in members.items()})


def _nearest_within(seed: Segment, others: list[Segment], reach: float) -> list[Segment]:
    """``seed`` and, nearest first, the other segments whose boxes keep the group's box diagonal within ``reach``."""
    group, lo, hi = [seed], seed.lower, seed.upper
    for h in sorted((h for h in others if h.id != seed.id),
                    key=lambda h: float(np.linalg.norm(h.centroid - seed.centroid))):
        lo2, hi2 = np.minimum(lo, h.lower), np.maximum(hi, h.upper)
        if np.linalg.norm(hi2 - lo2) <= reach:
            group.append(h)
            lo, hi = lo2, hi2
    return group


def _fit_parts(ctx: StageContext, items: list[CompositeItem], segments: list[Segment]) -> list[Segment]:
    """Fit the catalogue parts to the new segments. Segments that one fitted part explains together (a bracket's
    plate and leg, parted where the leg hides the corner from every station) become one segment: its seed is the
    largest, joined by the nearest other new segments (artefacts too) while all fit in the part's size. A segment
    records the best accepted fit; an ambiguous or poor fit records none."""
    from pathlib import Path

    from .parts import fit_part, load_part

    parts = []
    for k, p in enumerate(ctx.params.parts):
        path = Path(p.path) if Path(p.path).is_absolute() else Path(ctx.epoch.workflow_dir) / p.path
        if not path.is_file():
            raise ValueError(f"parts[{k}] {p.name!r}: no model file {path}")
        parts.append(load_part(p.name, path, p.max_rms, ctx.seed))
    keys = {it.key: it for it in items}
    new = [g for g in segments if g.kind == "new"]
    points = {g.id: np.vstack([keys[k].dataset.element_positions()[idx] for k, idx in g.members.items()])
              for g in new}
    taken: set[int] = set()
    out, record = [], []
    for g in new:  # largest first
        if g.id in taken or g.artefact:
            continue
        taken.add(g.id)
        fits = []
        for part in parts:
            group = _nearest_within(g, [h for h in new if h.id not in taken], 1.2 * part.diagonal)
            # the group first (it must fit as one part), then the segment alone if it is no larger than the part
            for cand in ([group] if len(group) > 1 else []) + [[g]]:
                if len(cand) == 1 and np.linalg.norm(g.upper - g.lower) > 1.5 * part.diagonal:
                    continue
                f = fit_part(np.vstack([points[h.id] for h in cand]), part, ctx.rng)
                fits.append((f, part, cand))
                if f.accepted:
                    break
        ok = [fit for fit in fits if fit[0].accepted]
        best, joined = None, [g]
        if ok:
            best, model, cand = min(ok, key=lambda fpc: (-len(fpc[2]), fpc[0].rms))
            to_part = np.linalg.inv(best.pose)
            d = [model.distance(to_part, np.vstack([points[h.id] for h in cand]))]
            joined, held = list(cand), {h.id for h in cand}
            # the other pieces the fitted part explains: new segments nearby whose elements lie on its surface
            for h in new:
                if h.id in taken or h.id in held or np.linalg.norm(h.centroid - best.centre) > model.diagonal:
                    continue
                dh = model.distance(to_part, points[h.id])
                if np.mean(dh <= model.max_rms) >= 0.9:
                    joined.append(h)
                    d.append(dh)
            if len(joined) > 1:  # scored again on everything it now holds
                d_all = np.concatenate(d)
                best = dataclasses.replace(best, rms=float(np.sqrt(np.mean(d_all**2))),
                                           fitness=float(np.mean(d_all <= model.max_rms)))
        taken.update(h.id for h in joined)
        seg = _merged(joined, points) if len(joined) > 1 else g
        record.append({"segment": g.id, "joined_sizes": [h.size for h in joined[1:]],
                       "fitted": None if best is None else best.part,
                       "tried": [{"part": f.part, "elements": int(sum(h.size for h in cand)), "rms": f.rms,
                                  "fitness": f.fitness, "ambiguous": f.ambiguous} for f, _, cand in fits]})
        out.append(seg if best is None else dataclasses.replace(
            seg, part=best.part, part_pose=best.pose, part_centre=best.centre, fit_rms=best.rms,
            fit_fitness=best.fitness))
    out += [g for g in new if g.id not in taken]  # the artefacts no part took
    out += [g for g in segments if g.kind != "new"]
    out.sort(key=lambda g: (g.kind != "new", g.artefact, -g.size, g.id))
    renumber = {g.id: k for k, g in enumerate(out)}
    for r in record:
        r["segment"] = renumber[r["segment"]]
    ctx.report(parts={"models": {p.name: {"path": str(p.path), "sha256": p.sha256, "max_rms": p.max_rms}
                                 for p in parts}, "segments": record})
    return [dataclasses.replace(g, id=k) for k, g in enumerate(out)]


def _fuse(ctx: StageContext, policy: str | None) -> dict[str, Any]:
    reference = ctx.get("reference") or Composite()
    changes = {c.query: c for c in ctx.get("change") or []}
    epoch = ctx.epoch
    items: list[CompositeItem] = []
    rov = ctx.get("rov")
    removed_now: dict[int, np.ndarray] = {}
    for it in reference.items:
        state = np.where(it.state == ChangeState.NEW, ChangeState.UNCHANGED, it.state).astype(np.uint8)
        visible = it.visible
        # hidden elements keep the reason they left with; what is still shown is "kept" until this epoch says more
        reason = np.where(it.visible, FusionReason.KEPT, it.reason).astype(np.uint8)
        ratio = np.where(it.visible, np.nan, it.reason_ratio)
        if rov is not None and it.key in rov.in_view:
            view, matched = rov.in_view[it.key], rov.matched[it.key]
            removed = view & ~matched & it.visible
            state = np.where(state == ChangeState.OUTSIDE_ROV, ChangeState.UNCHANGED, state).astype(np.uint8)
            state[it.visible & ~view] = ChangeState.OUTSIDE_ROV
            state[removed] = ChangeState.REMOVED
            reason[it.visible & ~view] = FusionReason.OUTSIDE_ROV
            reason[removed] = FusionReason.REMOVED
            visible = it.visible & ~removed
            removed_now[len(items)] = removed
        items.append(dataclasses.replace(it, state=state, visible=visible, reason=reason, reason_ratio=ratio))
    decision = None
    if policy is not None and reference.items:
        decision = _replacements(ctx, items, policy)
        counts = {}
        for i, mask in decision.replaced.items():
            if mask.any():
                it = items[i]
                items[i] = dataclasses.replace(
                    it, visible=it.visible & ~mask,
                    reason=np.where(mask, FusionReason.REPLACED, it.reason).astype(np.uint8),
                    reason_ratio=np.where(mask, decision.replaced_ratio[i], it.reason_ratio))
                counts[it.key] = int(mask.sum())
        ctx.report(fusion={"policy": policy, "replaced": counts,
                           "taking_over": {ctx["recent"][q].name: int(m.sum()) for q, m in decision.taking.items()},
                           "rule": "unchanged recent element in view replaces its nearest known element" +
                                   (" when its √det Σ is smaller" if policy == "most_reliable" else "")})
    for qi, ds in enumerate(ctx["recent"]):
        n = ds.n_elements
        ch = changes.get(qi)
        if ch is None and reference.items:
            raise ValueError(f"dataset {ds.name!r} has no change result although a reference exists")
        p_value = None
        reason = np.full(n, FusionReason.BASELINE, np.uint8)
        ratio = np.full(n, np.nan)
        if ch is None:
            visible = np.ones(n, dtype=bool)
            state = np.full(n, ChangeState.UNCHANGED, dtype=np.uint8)
            score = np.full(n, np.nan)
        else:
            visible, state, score, p_value = ch.mask, ch.state, ch.score, ch.p_value
            reason[:] = FusionReason.KNOWN_STAYS
            if decision is not None and qi in decision.reason:
                reason, ratio = decision.reason[qi], decision.ratio[qi]
            if decision is not None and qi in decision.taking:
                visible = visible | decision.taking[qi]
            reason = np.where(state == ChangeState.NEW, FusionReason.NEW, reason).astype(np.uint8)
        items.append(CompositeItem(key=f"{epoch.id}_{ds.name}", dataset=ds, epoch=epoch.id, state=state, score=score,
                                   source_epoch=np.full(n, epoch.index, dtype=np.int32), visible=visible,
                                   p_value=p_value, reason=reason, reason_ratio=ratio))
    codes = np.bincount(np.concatenate([it.reason for it in items]), minlength=len(FusionReason)) if items else []
    ctx.report(reasons={r.name.lower(): int(codes[r]) for r in FusionReason if codes[r]})
    n_ref = len(reference.items)
    new_masks = {n_ref + qi: (items[n_ref + qi].state == ChangeState.NEW) & items[n_ref + qi].visible
                 for qi in range(len(ctx["recent"])) if reference.items}
    segments = _segments(items, new_masks, "new", ctx.params, 0)
    if ctx.params.parts:
        segments = _fit_parts(ctx, items, segments)
    segments += _segments(items, removed_now, "removed", ctx.params, len(segments))
    if segments:
        real = [g for g in segments if not g.artefact]
        ctx.report(segments={"new": sum(g.kind == "new" for g in real),
                             "removed": sum(g.kind == "removed" for g in real), "artefacts": len(segments) - len(real)})
    return {"composite": Composite(tuple(items), tuple(segments))}


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in fusions."""
    common = {"family": "fusion", "version": "1.2.0", "requires": ("recent",),
              "optional": ("reference", "change", "rov"), "provides": ("composite",), "check": _check}
    keep = "Known data stays; changed new elements come in; unchanged new ones are hidden."
    return [StageSpec(name="keep_unchanged", params=KeepUnchangedParams, run=_keep_unchanged, description=keep,
                      **common),
            StageSpec(name="keep_reference", params=KeepUnchangedParams, run=_keep_unchanged,
                      description=keep + " (the same as keep_unchanged)", **common),
            StageSpec(name="most_reliable", params=MostReliableParams, run=_most_reliable,
                      description="As keep_unchanged, but more precise new data replaces measured data in view.",
                      **common),
            StageSpec(name="replace_in_view", params=ReplaceInViewParams, run=_replace_in_view,
                      description="The newest data replaces what it images inside the region of view.", **common)]
