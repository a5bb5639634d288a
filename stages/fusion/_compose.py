"""The composite every fusion builds: the known items carried over (removal needs the region of view), the recent
items with their change states and reasons, the replacement rule where the policy has one, and the segments."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from gdt_pipeline import (
    ChangeState,
    Composite,
    CompositeItem,
    FusionReason,
    ItemView,
    RegionOfView,
    Segment,
    StageContext,
    StageSpec,
    family_stage,
)
from gdt_pipeline.coverage import within_pair_region

from ._fitting import fit_parts, part_problems
from ._moved import moved
from ._replace import Decision, replacements
from ._segments import SegmentParams, segments


def fusion_stage(name: str, params: type[SegmentParams], run: Callable[[StageContext], dict[str, Any]],
                 description: str, needs_rov: bool) -> StageSpec:
    """A fusion stage: it reads the recent data and, when there are, the reference, the change and the region of
    view; its catalogue parts are checked before a run, and ``needs_rov`` says whether its rule replaces elements
    in view (then a region of view must come first)."""
    # only a fusion without a region of view reads the matches (``confirmed``); one that needs it does not ask
    # for them, so the runner lets the correspondences and scores go before it (38 B a point in memory at 2 M)
    matches = () if needs_rov else ("correspondences", "scores")
    return family_stage("fusion", name=name, version="1.3.0", params=params, run=run, description=description,
                        optional=("reference", "change", "rov", *matches), validate=part_problems,
                        check=chain_check(name, needs_rov))


def chain_check(name: str, needs_rov: bool) -> Callable[[frozenset[str]], str | None]:
    """The static rule of fusion ``name`` on the slots before it: from the second epoch on it needs the change
    results and, when it replaces known data by what is in view (``needs_rov``), a region of view."""
    def check(available: frozenset[str]) -> str | None:
        if "reference" not in available:
            return None  # the first epoch is the baseline: nothing to compare, nothing to replace
        if "change" not in available:
            return f"fusion {name!r} needs slot 'change' once a reference exists (add distance and threshold stages)"
        if needs_rov and "rov" not in available:
            return (f"fusion {name!r} needs a region-of-view stage before it once a reference exists: new data "
                    f"replaces old only where its region of view encloses the old (add `uses: sensor_frustum`, or "
                    f"`manual_box`, before it)")
        return None

    return check


check_slots = chain_check("keep_unchanged", False)


def confirmed(ctx: StageContext, reference: Composite) -> list[np.ndarray]:
    """Per known item, the elements that a recent element decided unchanged was matched with (this epoch tested
    them and found them as they were)."""
    out = [np.zeros(it.dataset.n_elements, dtype=bool) for it in reference.items]
    corrs = {c.query: c for c in ctx.get("correspondences") or []}
    for s, ch in zip(ctx.get("scores") or [], ctx.get("change") or [], strict=False):
        corr = corrs.get(s.query)
        if corr is None or s.match is None or ch.query != s.query:
            continue
        won = s.match[(s.match >= 0) & (ch.state == ChangeState.UNCHANGED)]
        for item in np.unique(corr.ref_item[won]):
            out[item][corr.ref_element[won][corr.ref_item[won] == item]] = True
    # a known point another recent point won can still lie within an unchanged recent point's noise: tested too
    recent = [(ds, ch) for ds, ch in zip(ctx["recent"], ctx.get("change") or [], strict=False) if ds.uncertainty]
    known_points = [it.dataset.faces is None and it.dataset.uncertainty is not None for it in reference.items]
    if recent and any(known_points):  # against CAD alone the unchanged cloud (96 B a point) and its tree serve none
        cloud = np.concatenate([ds.element_positions()[ch.state == ChangeState.UNCHANGED] for ds, ch in recent])
        cloud_cov = np.concatenate([ds.element_covariance()[ch.state == ChangeState.UNCHANGED] for ds, ch in recent])
        tree = cKDTree(cloud) if len(cloud) else None
        for i, it in enumerate(reference.items):
            if tree is not None and known_points[i]:
                out[i] |= within_pair_region(it.dataset.points, it.dataset.element_covariance(), cloud, cloud_cov,
                                             tree)
    return out


def _untested(items: list[CompositeItem], tested: list[np.ndarray]) -> list[CompositeItem]:
    """Without a region of view: known elements no unchanged recent element confirmed are not comparable (nothing
    says whether they are still there), the confirmed ones unchanged."""
    out = []
    for it, seen in zip(items, tested, strict=True):
        judged = it.visible & np.isin(it.state, (ChangeState.UNCHANGED, ChangeState.NOT_COMPARABLE))
        state = it.state.copy()
        state[judged] = np.where(seen[judged], ChangeState.UNCHANGED, ChangeState.NOT_COMPARABLE)
        out.append(dataclasses.replace(it, state=state))
    return out


def _carried(reference: Composite, rov: RegionOfView | None, whole_parts: bool = False
             ) -> tuple[list[CompositeItem], dict[int, np.ndarray]]:
    """The known items with this epoch's states and reasons, and per item the elements removed now."""
    items: list[CompositeItem] = []
    removed_now: dict[int, np.ndarray] = {}
    for it in reference.items:
        reset = (ChangeState.NEW, ChangeState.NOT_COMPARABLE)
        state = np.where(np.isin(it.state, reset), ChangeState.UNCHANGED, it.state).astype(np.uint8)
        visible = it.visible
        # hidden elements keep the reason they left with; what is still shown is "kept" until this epoch says more
        reason = np.where(it.visible, FusionReason.KEPT, it.reason).astype(np.uint8)
        ratio = np.where(it.visible, np.nan, it.reason_ratio)
        seen = None if rov is None else rov.views.get(it.key)
        if seen is not None:
            view, matched = seen.in_view, seen.matched
            removed = view & ~matched & it.visible
            if whole_parts and _gone_whole(it, seen):
                removed = it.visible.copy()
            state = np.where(state == ChangeState.OUTSIDE_ROV, ChangeState.UNCHANGED, state).astype(np.uint8)
            state[it.visible & ~view] = ChangeState.OUTSIDE_ROV
            state[removed] = ChangeState.REMOVED
            reason[it.visible & ~view] = FusionReason.OUTSIDE_ROV
            reason[removed] = FusionReason.REMOVED
            visible = it.visible & ~removed
            removed_now[len(items)] = removed
            areas = _areas(it, seen)
        else:
            areas = {}
        items.append(dataclasses.replace(it, state=state, visible=visible, reason=reason, reason_ratio=ratio,
                                         **areas))
    return items, removed_now


def _gone_whole(it: CompositeItem, seen: ItemView) -> bool:
    """Whether a mesh part was seen on at least a tenth of its (visible) area, all of that seen through: a rigid
    part is there or not, so its faces no station saw went with it."""
    if it.dataset.faces is None or seen.removed_fraction is None or (seen.in_view & seen.matched & it.visible).any():
        return False
    area = it.dataset.facet_areas() * it.visible
    return bool(area.sum() > 0 and (area * seen.removed_fraction).sum() >= 0.1 * area.sum())


def _areas(it: CompositeItem, seen: ItemView) -> dict[str, np.ndarray]:
    """This epoch's shares of area seen and removed where the region of view judged the item by area; elements
    hidden before keep the shares they left with."""
    if seen.seen_fraction is None or seen.removed_fraction is None:
        return {}
    out = {}
    for name, now in (("area_seen", seen.seen_fraction), ("area_removed", seen.removed_fraction)):
        before = getattr(it, name)
        before = np.full(len(now), np.nan) if before is None else before
        out[name] = np.where(it.visible, now, before)
    return out


def _replace(ctx: StageContext, items: list[CompositeItem], policy: str) -> Decision:
    """Apply the replacement rule to the known items (replaced elements are hidden, not dropped) and report it."""
    decision = replacements(ctx, items, policy)
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
    return decision


def _recent(ctx: StageContext, has_reference: bool, decision: Decision | None) -> list[CompositeItem]:
    """The recent datasets as items of this epoch: changed elements shown, unchanged ones hidden unless they take
    the place of known ones; the first epoch's data is the baseline."""
    changes = {c.query: c for c in ctx.get("change") or []}
    epoch = ctx.epoch
    items = []
    for qi, ds in enumerate(ctx["recent"]):
        n = ds.n_elements
        ch = changes.get(qi)
        if ch is None and has_reference:
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
            reason = np.where(state == ChangeState.NOT_COMPARABLE, FusionReason.EXTENDS, reason).astype(np.uint8)
        items.append(CompositeItem(key=f"{epoch.id}_{ds.name}", dataset=ds, epoch=epoch.id, state=state, score=score,
                                   source_epoch=np.full(n, epoch.index, dtype=np.int32), visible=visible,
                                   p_value=p_value, reason=reason, reason_ratio=ratio))
    return items


def _segmented(ctx: StageContext, items: list[CompositeItem], n_ref: int, removed_now: dict[int, np.ndarray]
               ) -> list[Segment]:
    """The new segments (fitted to the catalogue parts, if any) and then the removed ones, reported."""
    new_masks = {n_ref + qi: (items[n_ref + qi].state == ChangeState.NEW) & items[n_ref + qi].visible
                 for qi in range(len(ctx["recent"])) if n_ref}
    found = segments(items, new_masks, "new", ctx.params, 0)
    if ctx.params.parts:
        found = fit_parts(ctx, items, found)
    found += segments(items, removed_now, "removed", ctx.params, len(found))
    if ctx.params.moved:
        found = moved(ctx, items, found)
    if found:
        real = [g for g in found if not g.artefact]
        ctx.report(segments={"new": sum(g.kind == "new" for g in real),
                             "removed": sum(g.kind == "removed" for g in real), "artefacts": len(found) - len(real)})
    return found


def fuse(ctx: StageContext, policy: str | None) -> dict[str, Any]:
    """The composite of this epoch under ``policy`` (None: keep_unchanged, no replacement)."""
    reference = ctx.get("reference") or Composite()
    items, removed_now = _carried(reference, ctx.get("rov"), ctx.params.whole_parts)
    if reference.items and ctx.get("rov") is None and ctx.get("change") is not None:
        items = _untested(items, confirmed(ctx, reference))
    decision = None
    if policy is not None and reference.items:
        decision = _replace(ctx, items, policy)
    items += _recent(ctx, bool(reference.items), decision)
    codes = np.bincount(np.concatenate([it.reason for it in items]), minlength=len(FusionReason)) if items else []
    ctx.report(reasons={r.name.lower(): int(codes[r]) for r in FusionReason if codes[r]})
    found = _segmented(ctx, items, len(reference.items), removed_now)
    return {"composite": Composite(tuple(items), tuple(found))}
