"""The region of view judged by depth images (``sight: depth``): every reference element is sampled over its area,
each sample is looked at from every station whose volume holds it and which it faces, and an element is in view
where a station saw its place: present where measured surface lies at its depth, removed where the station saw past
it. The element's share of removed and seen area is kept."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gdt_pipeline import Composite, Dataset, RegionOfView

from ._depth import HIDDEN, NONE, PRESENT, THROUGH, DepthImage, Station, build_image, classify
from ._samples import area_samples

MAX_SAMPLES = 4_000_000  # per reference item: beyond it, facets get fewer samples each


@dataclass
class DepthView:
    """Per reference item: in view, matched (confirmed present), and the shares of its area seen and removed."""

    in_view: dict[str, np.ndarray] = field(default_factory=dict)
    matched: dict[str, np.ndarray] = field(default_factory=dict)
    seen_fraction: dict[str, np.ndarray] = field(default_factory=dict)
    removed_fraction: dict[str, np.ndarray] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=lambda: {"samples": 0, "present": 0, "through": 0, "hidden": 0,
                                                            "unseen": 0})


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
        pts = np.vstack([p for p, _ in parts]) if parts else np.zeros((0, 3))
        covs = [c if c.ndim == 3 else np.broadcast_to(c, (len(p), 3, 3)) for p, c in parts]
        images.append(build_image(st, pts, np.concatenate(covs) if covs else np.zeros((0, 3, 3)), pixel_scale))
    return images


def sample_states(ds: Dataset, visible: np.ndarray, inside: np.ndarray, pos: np.ndarray, owner: np.ndarray,
                  stations: list[Station], images: list[DepthImage | None], p: Any) -> np.ndarray:
    """The state of each sample: the largest code any station gives it (PRESENT over THROUGH over HIDDEN)."""
    state = np.zeros(len(pos), dtype=np.int8)
    cov = ds.element_covariance() if ds.uncertainty is not None else np.zeros((ds.n_elements, 3, 3))
    normals = ds.facet_normals() if ds.faces is not None else None
    todo = np.flatnonzero(inside & visible[owner])
    for st, img in zip(stations, images, strict=True):
        if img is None or not todo.size:
            continue
        cand = todo[st.contains(pos[todo])]
        if normals is not None and p.cull_back_faces:
            cand = cand[np.einsum("ij,ij->i", normals[owner[cand]], st.eye - pos[cand]) > 0]
        if cand.size:
            code = classify(img, pos[cand], cov[owner[cand]], None if normals is None else normals[owner[cand]],
                            p.k_sigma)
            state[cand] = np.maximum(state[cand], code)
        todo = todo[state[todo] != PRESENT]
    return state


def depth_view(reference: Composite, rov: RegionOfView, recent: list[Dataset], stations: list[Station],
               spacing: float, p: Any) -> DepthView:
    """In view, matched and the shares of area seen and removed, per reference item."""
    images = depth_images(stations, recent, p.pixel_scale)
    out = DepthView()
    for item in reference.items:
        ds = item.dataset
        n = ds.n_elements
        area_spacing = max(spacing, np.sqrt(_total_area(ds) / MAX_SAMPLES)) if ds.faces is not None else spacing
        pos, owner = area_samples(ds, area_spacing, p.samples_per_facet)
        state = sample_states(ds, item.visible, rov.contains(pos), pos, owner, stations, images, p)
        per = np.bincount(owner, minlength=n).astype(np.float64)
        present = np.bincount(owner, weights=state == PRESENT, minlength=n)
        through = np.bincount(owner, weights=state == THROUGH, minlength=n)
        seen = present + through
        out.in_view[item.key] = seen > 0
        out.matched[item.key] = (seen > 0) & (present >= through)
        out.seen_fraction[item.key] = seen / np.maximum(per, 1)
        out.removed_fraction[item.key] = through / np.maximum(per, 1)
        for name, code in (("present", PRESENT), ("through", THROUGH), ("hidden", HIDDEN), ("unseen", NONE)):
            out.counts[name] += int(np.sum(state == code))
        out.counts["samples"] += len(state)
    return out


def _total_area(ds: Dataset) -> float:
    tri = ds.points[ds.faces]
    return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


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
    elements = {"in_view": sum(int(v.sum()) for v in view.in_view.values()),
                "unmatched_in_view": sum(int((v & ~view.matched[k]).sum()) for k, v in view.in_view.items())}
    ctx.report(region_of_view={"parts": parts, "sight": "depth", "stations": len(stations), "k_sigma": p.k_sigma,
                               "spacing": spacing, "samples": view.counts, **elements})
    ctx.log.info("region of view (depth images, %d stations): %d samples: %d present, %d seen through, %d hidden, "
                 "%d unseen; %d elements in view of which %d removed", len(stations), view.counts["samples"],
                 view.counts["present"], view.counts["through"], view.counts["hidden"], view.counts["unseen"],
                 elements["in_view"], elements["unmatched_in_view"])
    return {"rov": RegionOfView(rov.vertices, rov.faces, rov.parts, in_view=view.in_view, matched=view.matched,
                                method="; ".join(parts) + "; depth images", seen_fraction=view.seen_fraction,
                                removed_fraction=view.removed_fraction)}
