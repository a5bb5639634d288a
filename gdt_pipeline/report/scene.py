"""What the report's 3-D view draws, read from the twin set by set: a census of every set (what is shown, how many
per state), then the shown facets per layer and the shown points subsampled on one voxel grid to the budget.

Shown are the elements in the composite at the epoch and, as ghosts, those it removed (state removed, visible at
the previous epoch, hidden now); elements hidden before stay out. A layer is a change state and the epoch that
supplied the elements (``source_epoch``): the view draws one trace per layer, so each can be toggled. Large point
sets in payload layers are drawn from their decimated previews unless the budget asks for more points than those
hold; no set's arrays are read all at once but its points, and those of a payload set only then.
"""

from __future__ import annotations

import contextlib
import ctypes
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from twin_store import STATE_NAMES, LeanSet, TwinStore, preview_rows

from .voxels import CHUNK, VoxelSampler

REMOVED = STATE_NAMES.index("removed")
Layer = tuple[int, int]  # (change state, source epoch index)
NO_LAYER = np.iinfo(np.uint16).max  # a layer id: the element is not shown
# a payload set is read whole (rather than its preview) only up to this many points, or 4 × the budget if more:
# its float32 points are held at once (USD reads an array whole), 30 MB here, and the report's peak RSS must stay
# within 200 MB at the default budget (docs/report.md)
FULL_READ_POINTS = 2_500_000


@dataclass(frozen=True)
class SetCensus:
    """One element set at the epoch: sizes and what the view shows of it."""

    key: str
    kind: str
    elements: int
    visible: int
    shown: int  # visible, plus the ghosts of what this epoch removed
    by_state: tuple[int, ...]  # visible elements per change state (removed: those this epoch removed)
    new_here: bool
    preview: bool  # a payload set with a decimated preview


@dataclass
class SceneData:
    """The 3-D view's content, coordinates float32 relative to ``centre`` (the twin's bounding-box centre)."""

    centre: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    points: dict[Layer, np.ndarray] = field(default_factory=dict)
    meshes: dict[Layer, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    points_total: int = 0
    points_shown: int = 0
    facets_shown: int = 0
    voxel: float = 0.0
    from_previews: list[str] = field(default_factory=list)


def shown_mask(es: LeanSet, state: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Elements the view draws: visible ones, and those this epoch removed (visible before, hidden now)."""
    before = es.field_before("visible")
    if before is None or len(before) != len(visible):
        return visible.copy()
    return visible | ((state == REMOVED) & before)


def census(store: TwinStore, epoch: str) -> tuple[list[SetCensus], np.ndarray, np.ndarray]:
    """Per set what it holds and what is shown, and the world bounds of the whole twin (lower, upper)."""
    out, lows, highs = [], [], []
    for es in store.iter_sets(epoch):
        state, visible = es.field("state"), es.field("visible")
        shown = shown_mask(es, state, visible)
        counted = np.bincount(state[visible], minlength=len(STATE_NAMES))[:len(STATE_NAMES)]
        counted[REMOVED] = int(np.sum(shown & ~visible))
        out.append(SetCensus(es.key, es.kind, len(state), int(visible.sum()), int(shown.sum()),
                             tuple(int(c) for c in counted), es.new_here, es.has_preview))
        lo, hi = es.bounds()
        lows.append(lo)
        highs.append(hi)
    if not out:
        return out, np.zeros(3), np.zeros(3)
    return out, np.min(lows, axis=0), np.max(highs, axis=0)


def _layers(state: np.ndarray, source: np.ndarray, shown: np.ndarray) -> Iterator[tuple[Layer, np.ndarray]]:
    """The shown elements of each layer, as index arrays."""
    code = state.astype(np.int64) * (1 << 32) + source.astype(np.int64)
    for value in np.unique(code[shown]):
        yield (int(value >> 32), int(value & 0xFFFFFFFF)), np.flatnonzero(shown & (code == value))


def _layer_ids(es: LeanSet, rows: np.ndarray | None) -> tuple[np.ndarray, list[Layer]]:
    """Per element (or per preview row) the index of its layer in the returned list, NO_LAYER where not shown: one
    uint16 an element in place of the state, source epoch and shown arrays while the set's points are held."""
    state = es.field("state")
    shown = shown_mask(es, state, es.field("visible"))
    source = es.field("source_epoch")
    if rows is not None:
        state, source, shown = state[rows], source[rows], shown[rows]
    ids = np.full(len(state), NO_LAYER, dtype=np.uint16)
    layers: list[Layer] = []
    for start in range(0, len(state), CHUNK):
        part = slice(start, start + CHUNK)
        for layer, idx in _layers(state[part], source[part], shown[part]):
            if layer not in layers:
                layers.append(layer)
            ids[part][idx] = layers.index(layer)
    return ids, layers


def _feed_points(es: LeanSet, sampler: VoxelSampler, centre: np.ndarray, from_preview: bool) -> bool:
    """Feed a point set's shown points (all, or its preview's) to the sampler, a chunk at a time; False when the
    preview was asked for but does not match the set (its own points were read instead)."""
    preview = es.preview(len(es.field("state"))) if from_preview else None
    ids, layers = _layer_ids(es, preview[2] if preview is not None else None)
    release_freed_memory()  # the per-element values are gone: their heap goes back before the points come in
    # a set written in parts comes part by part, so that one part's points are held, not the set's
    pieces, origin = ([(0, preview[0])], preview[1]) if preview is not None else es.point_parts()
    offset = (origin - centre).astype(np.float32)
    for first, local in pieces:
        for start in range(0, len(local), CHUNK):
            chunk = local[start:start + CHUNK]
            part = ids[first + start:first + start + len(chunk)]
            for k in np.unique(part[part != NO_LAYER]):
                sampler.add(layers[k], chunk[part == k] + offset)
    return preview is not None


def release_freed_memory() -> None:
    """Hand the heap's free pages back to the system (glibc's ``malloc_trim``). Without it the arrays of a set,
    once freed, stay in the process's RSS as heap the allocator keeps, and the next set's come on top."""
    with contextlib.suppress(OSError, AttributeError):  # not glibc: its allocator returns memory by its own rules
        ctypes.CDLL(None).malloc_trim(0)


def _mesh_layers(es: LeanSet, centre: np.ndarray) -> Iterator[tuple[Layer, np.ndarray, np.ndarray]]:
    """Per layer of a mesh its shown facets: the vertices they use (float32, relative) and faces into those."""
    state, visible, source = es.field("state"), es.field("visible"), es.field("source_epoch")
    shown = shown_mask(es, state, visible)
    if not shown.any():
        return
    local, origin = es.points()
    faces = es.faces()
    offset = (origin - centre).astype(np.float32)
    for layer, idx in _layers(state, source, shown):
        used, remapped = np.unique(faces[idx], return_inverse=True)
        yield layer, local[used] + offset, remapped.reshape(-1, 3).astype(np.int32)


def _merge_meshes(parts: dict[Layer, list[tuple[np.ndarray, np.ndarray]]]) -> dict[Layer, tuple[np.ndarray,
                                                                                                 np.ndarray]]:
    out = {}
    for layer, pieces in parts.items():
        offsets = np.cumsum([0] + [len(v) for v, _ in pieces[:-1]])
        out[layer] = (np.concatenate([v for v, _ in pieces]),
                      np.concatenate([f + np.int32(o) for (_, f), o in zip(pieces, offsets, strict=True)]))
    return out


def use_preview(entry: SetCensus, budget: int, points_total: int, preview_points: int) -> bool:
    """Whether a payload set is drawn from its preview (every k-th point): unless the budget asks for more of its
    points (all the shown points fit it, or it can draw a larger share of them than the preview holds of the set),
    and then only if its points, read whole, fit the memory the budget implies (``FULL_READ_POINTS``)."""
    if not entry.preview:
        return False
    asks_more = points_total <= budget or budget * entry.elements > preview_points * points_total
    return not asks_more or entry.elements > max(FULL_READ_POINTS, 4 * budget)


def scene_data(store: TwinStore, epoch: str, sets: list[SetCensus], bounds: tuple[np.ndarray, np.ndarray],
               budget: int) -> SceneData:
    """The shown facets per layer and the shown points, voxel-subsampled to ``budget``, relative to the centre."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds)
    centre = (lo + hi) / 2
    data = SceneData(centre=centre, lower=(lo - centre).astype(np.float32), upper=(hi - centre).astype(np.float32))
    data.points_total = sum(s.shown for s in sets if s.kind == "points")
    sampler = VoxelSampler(budget, data.lower, data.upper)
    meshes: dict[Layer, list[tuple[np.ndarray, np.ndarray]]] = {}
    info = {s.key: s for s in sets}
    for es in store.iter_sets(epoch):
        entry = info[es.key]
        if entry.shown == 0:
            continue
        if es.kind == "mesh":
            for layer, verts, faces in _mesh_layers(es, centre):
                meshes.setdefault(layer, []).append((verts, faces))
                data.facets_shown += len(faces)
            continue
        if budget == 0:
            continue  # no points asked for: none read
        wanted = use_preview(entry, budget, data.points_total, len(preview_rows(entry.elements)))
        if _feed_points(es, sampler, centre, wanted):
            data.from_previews.append(es.key)
        release_freed_memory()
    data.meshes = _merge_meshes(meshes)
    data.points, data.voxel = sampler.result()
    del sampler
    release_freed_memory()
    data.points_shown = sum(len(v) for v in data.points.values())
    return data
