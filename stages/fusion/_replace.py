"""The replacement rule of ``most_reliable`` and ``replace_in_view``: which known elements in view the unchanged
recent elements image, and which of those they replace."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from gdt_pipeline import Change, ChangeState, CompositeItem, Dataset, FusionReason, RegionOfView, StageContext

from ._segments import spread

# unchanged recent elements ``_choose`` judges at a time
CHOOSE_PIECE = 1 << 20


@dataclasses.dataclass
class Decision:
    """What the replacement rule decided: per known item the replaced elements and their ratios, per recent
    dataset the taking elements and, for every unchanged recent element, its reason code and ratio."""

    replaced: dict[int, np.ndarray]
    replaced_ratio: dict[int, np.ndarray]
    taking: dict[int, np.ndarray]
    reason: dict[int, np.ndarray]
    ratio: dict[int, np.ndarray]


@dataclasses.dataclass
class KnownInView:
    """The known elements in view that recent data may replace (stacked over the items: position, owning item,
    element index, √det Σ and 3σ of the largest axis), their index and typical gap, and the design (CAD) elements in
    view that stay, with theirs."""

    pos: np.ndarray
    owner: np.ndarray
    elem: np.ndarray
    vol: np.ndarray
    own: np.ndarray
    tree: cKDTree | None
    gap: float
    design_tree: cKDTree | None
    design_gap: float


@dataclasses.dataclass
class Taking:
    """The unchanged recent elements that take the place of known ones: positions and √det Σ, per recent dataset."""

    pos: list[np.ndarray]
    vol: list[np.ndarray]


def _known_in_view(items: list[CompositeItem], rov: RegionOfView, keep_design: bool) -> KnownInView | None:
    """The visible known elements inside the region of view; None when there are none."""
    pos, owner, elem, design = [], [], [], []
    for i, it in enumerate(items):
        seen = rov.views.get(it.key)
        if seen is None:
            continue
        idx = np.flatnonzero(seen.in_view & it.visible)
        pos.append(it.dataset.element_positions()[idx])
        owner.append(np.full(idx.size, i))
        elem.append(idx)
        design.append(np.full(idx.size, it.dataset.role == "as-designed"))
    if not sum(len(p) for p in pos):
        return None
    all_pos, all_design = np.vstack(pos), np.concatenate(design)
    # the design stays under most_reliable: only measured known elements can be replaced
    sel_known = ~all_design if keep_design else np.ones(len(all_pos), bool)
    pos_a, owner_a, elem_a = all_pos[sel_known], np.concatenate(owner)[sel_known], np.concatenate(elem)[sel_known]
    design_tree = cKDTree(all_pos[all_design]) if keep_design and all_design.any() else None
    design_gap = (float(np.median(design_tree.query(design_tree.data, k=2, workers=-1)[0][:, 1]))
                  if design_tree is not None and design_tree.n > 1 else 0.0)
    tree = cKDTree(pos_a) if len(pos_a) else None
    ref_gap = float(np.median(tree.query(pos_a, k=2, workers=-1)[0][:, 1])) if len(pos_a) > 1 else 0.0
    own = np.zeros(len(pos_a))
    vol_known = np.full(len(pos_a), np.inf)
    for i in np.unique(owner_a):
        sel = owner_a == i
        vol_known[sel], sigma = spread(items[i].dataset, elem_a[sel])
        own[sel] = 3.0 * sigma
    return KnownInView(pos_a, owner_a, elem_a, vol_known, own, tree, ref_gap, design_tree, design_gap)


def _choose(qi: int, ds: Dataset, ch: Change, known: KnownInView, policy: str, ratio_limit: float | None,
            out: Decision, taking: Taking) -> None:
    """Why each unchanged element of one recent dataset does or does not take the place of the known element it
    images; the taking ones go into ``out.taking`` and ``taking``."""
    reason = np.full(ds.n_elements, FusionReason.KNOWN_STAYS, np.uint8)
    ratio = np.full(ds.n_elements, np.nan)
    out.reason[qi], out.ratio[qi] = reason, ratio
    cand = np.flatnonzero(ch.state == ChangeState.UNCHANGED)
    if not cand.size:
        return
    mask = np.zeros(ds.n_elements, bool)
    # in pieces: positions, spreads and nearest neighbours of every unchanged point were 64 B a point at once
    for start in range(0, len(cand), CHOOSE_PIECE):
        _choose_piece(cand[start:start + CHOOSE_PIECE], ds, known, policy, ratio_limit, reason, ratio, mask, taking)
    if known.tree is not None:
        out.taking[qi] = mask


def _choose_piece(cand: np.ndarray, ds: Dataset, known: KnownInView, policy: str, ratio_limit: float | None,
                  reason: np.ndarray, ratio: np.ndarray, mask: np.ndarray, taking: Taking) -> None:
    """``_choose`` for the unchanged elements ``cand`` of the dataset."""
    rpos = ds.element_positions()[cand]
    v_new, sigma = spread(ds, cand)
    spacing = 3.0 * sigma
    if known.design_tree is not None:
        d_design, _ = known.design_tree.query(rpos, workers=-1)
        reason[cand[d_design <= np.maximum(spacing, 2.0 * known.design_gap)]] = FusionReason.DESIGN_STAYS
    if known.tree is None:
        return
    d, j = known.tree.query(rpos, workers=-1)
    # an unchanged recent element images its nearest in-view known element when it lies within 3σ of either's
    # largest axis or twice the known data's spacing (a sparse noisy reference is farther away than the precise σ)
    near = d <= np.maximum(np.maximum(spacing, known.own[j]), 2.0 * known.gap)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = v_new / known.vol[j]
    take = near.copy()
    if policy == "most_reliable":
        take &= v_new < ratio_limit * known.vol[j]
        reason[cand[near & ~take]] = FusionReason.KNOWN_MORE_PRECISE
    reason[cand[take]] = FusionReason.REPLACES
    ratio[cand[near]] = np.where(np.isfinite(r[near]), r[near], np.nan)
    mask[cand[take]] = True
    taking.pos.append(rpos[take])
    taking.vol.append(v_new[take])


def _replace_known(known: KnownInView, taking: Taking, out: Decision) -> None:
    """Mark every known element the taking data images as replaced, not only the nearest of each: a known element
    within 3σ of its own largest axis (or twice the typical gap) of taking data."""
    dist, k = cKDTree(np.vstack(taking.pos)).query(known.pos, workers=-1)
    hit = dist <= np.maximum(known.own, 2.0 * known.gap)
    with np.errstate(invalid="ignore", divide="ignore"):
        r_known = np.concatenate(taking.vol)[k] / known.vol
    for i in np.unique(known.owner[hit]):
        sel = hit & (known.owner == i)
        out.replaced[i][known.elem[sel]] = True
        out.replaced_ratio[i][known.elem[sel]] = np.where(np.isfinite(r_known[sel]), r_known[sel], np.nan)


def replacements(ctx: StageContext, items: list[CompositeItem], policy: str) -> Decision:
    """Which known elements the unchanged recent elements replace, and why each unchanged recent element does or
    does not take their place."""
    rov = ctx.get("rov")
    if rov is None:
        raise ValueError(f"fusion {policy!r} needs a region-of-view stage before it (sensor_frustum or manual_box): "
                         f"new data replaces old only where its region of view encloses the old")
    changes = {c.query: c for c in ctx.get("change") or []}
    out = Decision({i: np.zeros(it.dataset.n_elements, bool) for i, it in enumerate(items)},
                   {i: np.full(it.dataset.n_elements, np.nan) for i, it in enumerate(items)}, {}, {}, {})
    keep_design = policy == "most_reliable" and not ctx.params.replace_design
    known = _known_in_view(items, rov, keep_design)
    if known is None:
        return out
    # replace_in_view has no ratio: its parameters do not carry one
    ratio_limit = ctx.params.ratio if policy == "most_reliable" else None
    taking = Taking([], [])
    for qi, ds in enumerate(ctx["recent"]):
        ch = changes.get(qi)
        if ch is not None:
            _choose(qi, ds, ch, known, policy, ratio_limit, out, taking)
    if not taking.pos or not sum(len(t) for t in taking.pos):
        return out
    _replace_known(known, taking, out)
    return out
