"""The region of view judged by depth images (``sight: depth``): every reference element is sampled over its area,
each sample is looked at from every station whose volume holds it and which it faces, and an element is in view
where a station saw its place: present where measured surface lies at its depth, removed where the station saw past
it. The element's share of removed and seen area is kept."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..memory import release_scratch_pages
from ..types import Composite, Dataset, ItemView, RegionOfView
from .contact import closed_parts, in_contact
from .depth import HIDDEN, NONE, PRESENT, THROUGH, DepthImage, Station, build_image, window_votes
from .occlusion import blocked_by_confirmed, confirmed_facets
from .samples import area_samples

MAX_SAMPLES = 4_000_000  # per reference item: beyond it, facets get fewer samples each
SAMPLE_CHUNK = 500_000  # samples a station judges at once


@dataclass
class DepthView:
    """Per reference item (by key) its view: in view, matched (confirmed present), and the shares of its area seen
    and removed; and how many samples came out which way."""

    views: dict[str, ItemView] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=lambda: {"samples": 0, "present": 0, "through": 0,
                                                            "hidden_or_no_points": 0, "unseen": 0})


def station_points(ds: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """What a dataset measured, as points with covariances: its points, or a mesh's vertices and facet centroids
    (with the facets' median covariance)."""
    cov = ds.element_covariance() if ds.uncertainty is not None else np.zeros((ds.n_elements, 3, 3))
    if ds.faces is None:
        return np.asarray(ds.points), cov
    pts = np.vstack([ds.points, ds.element_positions()])
    return pts, np.median(cov, axis=0) if len(cov) else np.zeros((3, 3))


def depth_images(stations: list[Station], recent: list[Dataset], pixel_scale: float) -> list[DepthImage | None]:
    """One depth image per station, of the recent datasets it measured."""
    images = []
    for st in stations:
        parts = [station_points(recent[i]) for i in st.datasets]
        if len(parts) == 1:  # a station's one scan: its image keeps the dataset's own arrays (96 B a point)
            pts, cov = parts[0][0], _per_point(*parts[0])
        else:
            pts = np.vstack([p for p, _ in parts]) if parts else np.zeros((0, 3))
            cov = np.concatenate([_per_point(p, c) for p, c in parts]) if parts else np.zeros((0, 3, 3))
        images.append(build_image(st, pts, cov, pixel_scale))
        release_scratch_pages()  # the scan's pages in scratch files it read: one station's at a time, not all
    return images


def _per_point(pts: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariances as (N,3,3), one per point (a shared (3,3) one broadcast, not copied)."""
    return cov if cov.ndim == 3 else np.broadcast_to(cov, (len(pts), 3, 3))


@dataclass
class SampleStates:
    """One reference item's samples: positions, owning elements, states, and per station which samples it saw
    through."""

    pos: np.ndarray
    owner: np.ndarray
    state: np.ndarray
    through: list[tuple[int, np.ndarray]]


def sample_states(ds: Dataset, visible: np.ndarray, inside: np.ndarray, pos: np.ndarray, owner: np.ndarray,
                  stations: list[Station], images: list[DepthImage | None], p: Any) -> SampleStates:
    """The state of each sample from the votes of every station that could see it, summed (a near station's
    many points outweigh a far one's few): present where at least as many points lie at it as behind it, seen
    through where more lie behind; HIDDEN where stations looked but had surface in front of it or no points at it;
    NONE where no station could look."""
    votes = np.zeros((2, len(pos)), dtype=np.int32)
    looked_at = np.zeros(len(pos), dtype=bool)
    through = []
    cov = ds.element_covariance() if ds.uncertainty is not None else np.zeros((ds.n_elements, 3, 3))
    tris = ds.points[ds.faces] if ds.faces is not None else None
    normals = ds.facet_normals() if ds.faces is not None else None
    todo = np.flatnonzero(inside & visible[owner])
    for k, (st, img) in enumerate(zip(stations, images, strict=True)):
        if img is None or not todo.size:
            continue
        seen_through = []
        for s0 in range(0, len(todo), SAMPLE_CHUNK):  # the gathers below are 24-72 B a sample: a chunk at a time
            cand = todo[s0:s0 + SAMPLE_CHUNK]
            cand = cand[st.contains(pos[cand])]
            if normals is not None and p.cull_back_faces:
                cand = cand[np.einsum("ij,ij->i", normals[owner[cand]], st.eye - pos[cand]) > 0]
            if cand.size:
                v = window_votes(img, pos[cand], cov, tris, p.k_sigma, owner=owner[cand])
                votes[:, cand] += v
                looked_at[cand] = True
                seen_through.append(cand[v[1] > 0])
                release_scratch_pages()  # the covariances gathered at random touched pages all over their file
        if seen_through:
            through.append((k, np.concatenate(seen_through)))
    at, behind = votes
    state = np.where((at > 0) & (at >= behind), PRESENT, np.where(behind > at, THROUGH,
                                                                  np.where(looked_at, HIDDEN, NONE)))
    return SampleStates(pos, owner, state.astype(np.int8), through)


def unblock(looked: SampleStates, stations: list[Station], confirmed: Any, start: float) -> None:
    """Samples seen through only along sight lines that a reference facet confirmed present crosses from its
    front become hidden: a CAD face inside another part (a web's face under its flange) is never seen, though the
    measured surface around the covering part's edge lies behind it."""
    through = looked.state == THROUGH
    clear = np.zeros(len(looked.state), dtype=bool)
    for k, idx in looked.through:
        idx = idx[through[idx] & ~clear[idx]]
        if not idx.size:
            continue
        eye = np.broadcast_to(stations[k].eye, (idx.size, 3))
        direction = eye - looked.pos[idx]
        length = np.linalg.norm(direction, axis=1, keepdims=True)
        origin = looked.pos[idx] + direction / np.maximum(length, 1e-300) * np.minimum(start, 0.5 * length)
        clear[idx[~blocked_by_confirmed(origin, eye, confirmed)]] = True
    looked.state[through & ~clear] = HIDDEN


def element_shares(looked: SampleStates, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per element: its number of samples, and how many were present and seen through."""
    per = np.bincount(looked.owner, minlength=n).astype(np.float64)
    present = np.bincount(looked.owner, weights=looked.state == PRESENT, minlength=n)
    return per, present, np.bincount(looked.owner, weights=looked.state == THROUGH, minlength=n)


def matched(looked: SampleStates, n: int) -> np.ndarray:
    """The elements confirmed present: seen, and found present on at least as many samples as seen through."""
    _, present, through = element_shares(looked, n)
    return (present > 0) & (present >= through)


def depth_view(reference: Composite, rov: RegionOfView, recent: list[Dataset], stations: list[Station],
               spacing: float, p: Any) -> DepthView:
    """In view, matched and the shares of area seen and removed, per reference item."""
    images = depth_images(stations, recent, p.pixel_scale)
    parts = closed_parts(reference)
    extent = max((float(np.ptp(it.dataset.points, axis=0).max()) for it in reference.items if len(it.dataset.points)),
                 default=1.0)
    looks = []
    for item in reference.items:
        ds = item.dataset
        area_spacing = spacing if ds.faces is None else max(spacing, float(np.sqrt(ds.facet_areas().sum() /
                                                                                     MAX_SAMPLES)))
        # a facet turned away from every station is judged by none (sample_states culls it per sample): one
        # sample carries its "not seen" as well as m² (the bottom of a part held 40 % of the samples)
        away = facing_no_station(ds, stations) if ds.faces is not None and p.cull_back_faces else None
        pos, owner = area_samples(ds, area_spacing, p.samples_per_facet, away)
        looked = rov.contains(pos)
        if ds.faces is not None:
            # float32 ray casting near the data: the probe steps clear of round-off at the scene's size
            ask = np.flatnonzero(looked)  # only samples inside the region can be in view at all
            looked[ask] = ~in_contact(pos[ask], ds.facet_normals(), parts, max(0.02 * spacing, 1e-5 * extent),
                                      owner=owner[ask])
        looks.append(sample_states(ds, item.visible, looked, pos, owner, stations, images, p))
    if p.confirmed_occlude:
        confirmed = confirmed_facets([(it.dataset, matched(lk, it.dataset.n_elements))
                                      for it, lk in zip(reference.items, looks, strict=True)
                                      if it.dataset.faces is not None])
        for lk in looks:
            unblock(lk, stations, confirmed, 3e-3 * spacing)
    out = DepthView()
    for item, lk in zip(reference.items, looks, strict=True):
        per, present, through = element_shares(lk, item.dataset.n_elements)
        seen = present + through
        out.views[item.key] = ItemView(seen > 0, matched(lk, item.dataset.n_elements), seen / np.maximum(per, 1),
                                       through / np.maximum(per, 1))
        for name, code in (("present", PRESENT), ("through", THROUGH), ("hidden_or_no_points", HIDDEN),
                           ("unseen", NONE)):
            out.counts[name] += int(np.sum(lk.state == code))
        out.counts["samples"] += len(lk.state)
    return out


def facing_no_station(ds: Dataset, stations: list[Station]) -> np.ndarray:
    """Per facet, whether every station lies behind its plane (at every corner: then at every point of it; a
    station within round-off of the plane counts as in front)."""
    normals = ds.facet_normals()
    tri = ds.points[ds.faces]
    tol = 1e-9 * np.linalg.norm(normals, axis=1) * max(float(np.ptp(ds.points, axis=0).max()), 1e-12)
    away = np.ones(len(tri), dtype=bool)
    for st in stations:
        front = np.einsum("fj,fkj->fk", normals, st.eye - tri).max(axis=1) > -tol
        away &= ~front
    return away


def default_stations(p: Any, recent: list[Dataset], rov: RegionOfView) -> list[Station]:
    """Stations when no frustum gives them: the parameters' viewpoints (each measured all recent data), else each
    recent dataset's own viewpoints; the whole volume is every station's."""
    if p.viewpoints:
        every = tuple(range(len(recent)))
        return [Station(np.asarray(vp, dtype=np.float64), rov.contains, every) for vp in p.viewpoints]
    out = [Station(np.asarray(vp, dtype=np.float64), rov.contains, (i,))
           for i, ds in enumerate(recent) if ds.viewpoints is not None for vp in np.atleast_2d(ds.viewpoints)]
    if not out:
        raise ValueError("sight: depth needs sensor positions: the inputs carry no viewpoints; state them under "
                         "'viewpoints' (on the inputs or the stage)")
    return out


def look_depth(ctx: Any, rov: RegionOfView, parts: list[str], stations: list[Station] | None, spacing: float
               ) -> dict[str, Any]:
    """The region of view by depth images, and the report of how."""
    p = ctx.params
    recent: list[Dataset] = ctx["recent"]
    reference: Composite = ctx.get("reference") or Composite()
    stations = default_stations(p, recent, rov) if p.viewpoints or not stations else stations
    view = depth_view(reference, rov, recent, stations, spacing, p)
    elements = {"in_view": sum(int(v.in_view.sum()) for v in view.views.values()),
                "unmatched_in_view": sum(int((v.in_view & ~v.matched).sum()) for v in view.views.values())}
    ctx.report(region_of_view={"parts": parts, "sight": "depth", "stations": len(stations), "k_sigma": p.k_sigma,
                               "spacing": spacing, "samples": view.counts, **elements})
    ctx.log.info("region of view (depth images, %d stations): %d samples: %d present, %d seen through, %d hidden "
                 "or without points, %d outside every station's view; %d elements in view of which %d removed",
                 len(stations), view.counts["samples"], view.counts["present"], view.counts["through"],
                 view.counts["hidden_or_no_points"], view.counts["unseen"],
                 elements["in_view"], elements["unmatched_in_view"])
    return {"rov": RegionOfView(rov.vertices, rov.faces, rov.parts, views=view.views,
                                method="; ".join(parts) + "; depth images")}
