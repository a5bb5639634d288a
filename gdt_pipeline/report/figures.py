"""The report's plotly figures as JSON-ready dicts: the 3-D view (one trace per layer, a hidden segment box) and
the histograms. Arrays go in as plotly.js typed arrays (``{"dtype": "f4", "bdata": base64}``, read by plotly.js
2.28 and later; the embedded one is checked in ``assets``), 4 bytes a number instead of a decimal string."""

from __future__ import annotations

import base64
from typing import Any

import numpy as np

from twin_store import STATE_COLORS, STATE_NAMES

from .histograms import HistogramGroup
from .scene import Layer, SceneData

TYPED = {np.dtype(np.float32): "f4", np.dtype(np.float64): "f8", np.dtype(np.int32): "i4", np.dtype(np.uint32): "u4"}
# how each change state is drawn: opacity, share of white mixed into its colour, the word the page uses for it.
# White as well as transparency: thousands of overlapping translucent markers add up to the full colour again.
STYLE = {0: (1.0, 0.0, "solid"), 1: (1.0, 0.0, "solid"), 2: (0.25, 0.55, "ghosted"), 3: (0.6, 0.5, "dimmed"),
         4: (0.8, 0.3, "dimmed")}
SOLID = (1.0, 0.0, "solid")
MARKER_PX = 2
BOX_COLOUR = "#ff8c00"
CAMERA = {"eye": {"x": 1.35, "y": -1.35, "z": 0.95}, "center": {"x": 0, "y": 0, "z": 0}}


def typed(values: np.ndarray) -> dict[str, str]:
    """A numpy array as a plotly.js typed array (little-endian bytes, base64)."""
    arr = np.ascontiguousarray(values)
    if arr.dtype not in TYPED:
        raise ValueError(f"no plotly.js typed array for dtype {arr.dtype}")
    return {"dtype": TYPED[arr.dtype], "bdata": base64.b64encode(arr.astype(arr.dtype.newbyteorder("<")).tobytes())
            .decode("ascii")}


def state_rgb(state: int) -> str:
    """The colour a change state is drawn in, as CSS ``rgb()``: the twin's ``STATE_COLORS``, mixed with white as
    ``STYLE`` says (ghosted and dimmed states)."""
    whiten = STYLE.get(state, SOLID)[1]
    base = STATE_COLORS[min(state, len(STATE_COLORS) - 1)].astype(np.float64)
    r, g, b = (round(float(c) * 255) for c in base + (1.0 - base) * whiten)
    return f"rgb({r},{g},{b})"


def plural(n: int, word: str) -> str:
    """``1 point``, ``2,000 points``."""
    return f"{n:,} {word}" + ("" if n == 1 else "s")


def state_name(state: int) -> str:
    """The name of a change state code (``code N`` for one the twin store does not know)."""
    return STATE_NAMES[state] if state < len(STATE_NAMES) else f"code {state}"


def _layer_traces(layer: Layer, data: SceneData, epochs: list[str]) -> list[dict[str, Any]]:
    """The mesh3d and scatter3d traces of one layer, in one legend group (the first carries the legend entry)."""
    state, source = layer
    epoch = epochs[source] if 0 <= source < len(epochs) else f"#{source}"
    opacity = STYLE.get(state, SOLID)[0]
    colour = state_rgb(state)
    meta = {"state": state_name(state), "epoch": epoch}
    common = {"legendgroup": f"{state_name(state)}:{epoch}", "opacity": opacity, "meta": meta,
              "hovertemplate": f"{state_name(state)}, from {epoch}<br>%{{x:.4g}}, %{{y:.4g}}, %{{z:.4g}}"
                               "<extra></extra>"}
    parts = []
    if layer in data.meshes:
        verts, faces = data.meshes[layer]
        parts.append({"type": "mesh3d", "x": typed(verts[:, 0]), "y": typed(verts[:, 1]), "z": typed(verts[:, 2]),
                      "i": typed(faces[:, 0]), "j": typed(faces[:, 1]), "k": typed(faces[:, 2]), "color": colour,
                      "flatshading": True, "lighting": {"ambient": 0.55, "diffuse": 0.6, "specular": 0.05},
                      "_count": plural(len(faces), "facet"), **common})
    if layer in data.points:
        xyz = data.points[layer]
        parts.append({"type": "scatter3d", "mode": "markers", "x": typed(xyz[:, 0]), "y": typed(xyz[:, 1]),
                      "z": typed(xyz[:, 2]), "marker": {"size": MARKER_PX, "color": colour},
                      "_count": plural(len(xyz), "point"), **common})
    label = f"{state_name(state).replace('_', ' ')}, from {epoch}: " + ", ".join(p.pop("_count") for p in parts)
    for k, p in enumerate(parts):
        p.update({"name": label, "showlegend": k == 0})
    return parts


def drawn_bounds(data: SceneData) -> tuple[np.ndarray, np.ndarray]:
    """The bounds of what the view draws (the whole twin's, hidden elements included, when it draws nothing)."""
    arrays = [*data.points.values(), *(verts for verts, _ in data.meshes.values())]
    arrays = [a for a in arrays if len(a)]
    if not arrays:
        return data.lower.astype(np.float64), data.upper.astype(np.float64)
    return (np.min([a.min(axis=0) for a in arrays], axis=0).astype(np.float64),
            np.max([a.max(axis=0) for a in arrays], axis=0).astype(np.float64))


def view_figure(data: SceneData, epochs: list[str], units: str, up_axis: str) -> dict[str, Any]:
    """The 3-D view: a trace per layer (state, then source epoch), a hidden segment box last, axes as a cube
    around what is drawn, with equal scales."""
    layers = sorted(set(data.points) | set(data.meshes))
    traces = [t for layer in layers for t in _layer_traces(layer, data, epochs)]
    traces.append({"type": "scatter3d", "mode": "lines", "x": [], "y": [], "z": [], "name": "segment",
                   "visible": False, "showlegend": False, "hoverinfo": "skip",
                   "line": {"color": BOX_COLOUR, "width": 6}})
    lower, upper = drawn_bounds(data)
    half = float(np.max(upper - lower)) / 2 * 1.05 or 1.0
    centre = (lower + upper) / 2
    axes = {f"{a}axis": {"range": [float(centre[i] - half), float(centre[i] + half)],
                         "title": {"text": f"{a} ({units})"}} for i, a in enumerate("xyz")}
    up = {"x": 0, "y": 0, "z": 1} if up_axis.upper() == "Z" else {"x": 0, "y": 1, "z": 0}
    # the scene right of the legend, so that the legend never covers the twin
    layout = {"scene": {**axes, "aspectmode": "cube", "camera": {**CAMERA, "up": up}, "domain": {"x": [0.22, 1]}},
              "margin": {"l": 0, "r": 0, "t": 0, "b": 0},
              "legend": {"groupclick": "togglegroup", "itemsizing": "constant", "x": 0, "y": 1},
              "uirevision": "keep", "paper_bgcolor": "#ffffff"}
    # the voxel grid of the subsample (size 0: every point), so that a reader can check one point per voxel
    grid = {"size": float(data.voxel), "origin": [float(v) for v in data.lower]}
    return {"data": traces, "layout": layout, "home": {k: v["range"] for k, v in axes.items()},
            "margin": half * 0.02, "voxel": grid}


def _step(edges: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return edges.astype(np.float64), np.append(counts, counts[-1] if len(counts) else 0).astype(np.float64)


def histogram_figure(group: HistogramGroup, title: str, xlabel: str) -> dict[str, Any]:
    """One figure: a step line per dataset, a dashed vertical line per distinct threshold (in the dataset's legend
    group, so toggling the dataset toggles its τ too)."""
    traces: list[dict[str, Any]] = []
    top = max((int(h.counts.max()) for h in group.histograms if h.counts.size), default=1)
    taus = {h.threshold for h in group.histograms if h.threshold is not None}
    shared = len(taus) == 1 and all(h.threshold is not None for h in group.histograms)
    for k, h in enumerate(group.histograms):
        x, y = _step(group.edges, h.counts)
        traces.append({"type": "scatter", "mode": "lines", "x": typed(x), "y": typed(y), "name": h.key,
                       "legendgroup": h.key, "line": {"shape": "hv", "width": 1.5},
                       "hovertemplate": f"{h.key}<br>%{{x:.4g}}: %{{y}} elements<extra></extra>"})
        if h.threshold is not None and (not shared or k == 0):
            name = f"τ = {h.threshold:.4g}" + (" (all datasets)" if shared else f" ({h.key})")
            traces.append({"type": "scatter", "mode": "lines", "x": [h.threshold, h.threshold], "y": [0, top],
                           "name": name, "legendgroup": "tau" if shared else h.key,
                           "line": {"dash": "dash", "color": "#222", "width": 1.5},
                           "hovertemplate": f"{name}<extra></extra>"})
    layout = {"title": {"text": title, "font": {"size": 14}}, "margin": {"l": 60, "r": 10, "t": 40, "b": 50},
              "xaxis": {"title": {"text": xlabel + (" (log scale)" if group.log else "")},
                        "type": "log" if group.log else "linear", "exponentformat": "e"},
              "yaxis": {"title": {"text": "elements"}, "rangemode": "tozero"}, "height": 360,
              "legend": {"font": {"size": 10}}}
    return {"data": traces, "layout": layout}
