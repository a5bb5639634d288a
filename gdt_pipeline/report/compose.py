"""The report's sections from what was read: the 3-D view with its toggles and the subsample note, the segments,
the score and uncertainty histograms, and the provenance."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..types import Segment
from .figures import histogram_figure, view_figure
from .histograms import HistogramGroup
from .page import PageParts, toggles_html
from .scene import SceneData, SetCensus
from .tables import (
    counts_tables,
    esc,
    inputs_table,
    run_facts,
    segments_table,
    stages_table,
    uncertainty_notes,
)


def subsample_note(scene: SceneData, budget: int, units: str) -> str:
    """The sentence saying how many points the view shows, of how many, and how they were chosen."""
    how = (f"voxel subsample: one point per {scene.voxel:.3g} {esc(units)} voxel and layer, budget {budget:,}"
           if scene.voxel > 0 and budget > 0 else "budget 0: no points drawn" if budget == 0 and scene.points_total
           else f"no subsample needed, budget {budget:,}")
    text = f"showing {scene.points_shown:,} of {scene.points_total:,} points ({how})"
    if scene.from_previews:
        keys = ", ".join(esc(k) for k in scene.from_previews)
        text += (f"; the payload sets {keys} are drawn from their decimated previews (every k-th point), as the "
                 f"budget asks for no more of their points or their own would not fit the report's memory bound")
    return f"{text}; {scene.facets_shown:,} facets."


def view_section(scene: SceneData, figure: dict[str, Any], epochs: list[str], budget: int, units: str) -> str:
    """The 3-D view: what it shows, how to use its toggles, where its coordinates are from."""
    layers = [(int(s), epochs[e] if 0 <= e < len(epochs) else f"#{e}") for s, e in
              sorted(set(scene.points) | set(scene.meshes))]
    c = ", ".join(f"{v:.6g}" for v in scene.centre)
    return (f'<section id="view"><h2>3-D view</h2>'
            f'<p class="note" id="subsample">{subsample_note(scene, budget, units)}</p>'
            f"{toggles_html(layers, epochs)}"
            f'<p class="legend-help">Colours are the change state of this epoch: unchanged and new solid, removed '
            f"(hidden by this epoch) ghosted, outside the region of view dimmed, not comparable (nothing in the other "
            f"epoch to compare with, or not tested) amber; elements hidden by earlier epochs "
            f"are not drawn. The check boxes show or hide every layer of a change state, or every layer an epoch "
            f"supplied (a layer is drawn when both its boxes are ticked). Each legend entry is one layer (a state "
            f"and the epoch that supplied its elements): click it to hide or show that layer, double-click to show "
            f"it alone. Click a row of the segments table to frame that segment; <b>Whole twin</b> frames "
            f"everything again. Coordinates are in {esc(units)}, relative to the twin's bounding-box centre "
            f"({esc(c)}) {esc(units)}: add it for world coordinates.</p>"
            f'<div id="view3d"></div></section>')


def histogram_section(group: HistogramGroup, div: str, title: str, xlabel: str, intro: str
                      ) -> tuple[str, dict[str, Any] | None]:
    """A histogram section (or a line saying there is nothing to count) and its figure for the page's data."""
    counted = sum(h.values for h in group.histograms)
    if counted == 0:
        return f"<p>{esc(intro)}: no finite values in this epoch's datasets.</p>", None
    notes = []
    for h in group.histograms:
        line = f"<code>{esc(h.key)}</code>: {h.values:,} values"
        if h.off_axis:
            line += f" ({h.off_axis:,} of them ≤ 0, off the logarithmic axis)"
        if group.field == "score":
            line += f"; {esc(h.note)}" + (f", τ = {h.threshold:.4g}" if h.threshold is not None and "τ =" not in
                                          h.note else "")
        notes.append(f"<li>{line}</li>")
    html = (f"<p>{esc(intro)}</p><div class=hist id=\"{div}\"></div><details><summary>per dataset</summary>"
            f"<ul>{''.join(notes)}</ul></details>")
    return html, {"id": div, "figure": histogram_figure(group, title, xlabel)}


def segment_boxes(segments: list[Segment], centre: np.ndarray) -> dict[str, Any]:
    """Per segment id its box relative to the view's centre (float, for the page's script)."""
    return {str(int(s.id)): {"lower": [float(v) for v in np.asarray(s.lower, np.float64) - centre],
                             "upper": [float(v) for v in np.asarray(s.upper, np.float64) - centre]}
            for s in segments}


def page_parts(*, twin: str, epoch: str, epochs: list[str], provenance: dict[str, Any], sets: list[SetCensus],
               scene: SceneData, segments: list[Segment], scores: HistogramGroup, sigmas: HistogramGroup,
               budget: int, units: str, up_axis: str) -> PageParts:
    """Every section of the page and the data its script draws."""
    figure = view_figure(scene, epochs, units, up_axis)
    score_html, score_fig = histogram_section(
        scores, "hist-score", f"Change scores of the datasets of {epoch}", "change score",
        "Finite change scores of the elements this epoch's datasets brought in, one line per dataset, the "
        "threshold the epoch cut them at dashed")
    sigma_html, sigma_fig = histogram_section(
        sigmas, "hist-uncertainty", f"Uncertainty σ of the datasets of {epoch}", f"RMS σ ({units})",
        "RMS standard deviation σ of each element of this epoch's datasets, as its uncertainty stage set it")
    kinds = {"new": sum(s.kind == "new" for s in segments), "removed": sum(s.kind == "removed" for s in segments)}
    role = (provenance.get("epoch") or {}).get("role", "?")
    header = (f"<header><h1>{esc(twin)} at epoch {esc(epoch)}</h1><p>Epoch {esc(epoch)} ({esc(role)}) of "
              f"{esc(', '.join(epochs))}; twin units {esc(units)}, up axis {esc(up_axis)}.</p>"
              f'<nav><a href="#view">3-D view</a><a href="#segments-section">segments</a><a href="#scores">scores'
              f'</a><a href="#uncertainty">uncertainty</a><a href="#provenance">provenance</a></nav></header>')
    sections = [
        view_section(scene, figure, epochs, budget, units),
        f'<section id="segments-section"><h2>Segments of {esc(epoch)}</h2><p class="note">{kinds["new"]} new and '
        f"{kinds['removed']} removed segments (connected changed elements; artefacts are those below the fusion's "
        f"minimum size). Click a row to frame the segment in the 3-D view and draw its box.</p>"
        f'<div class="scroll">{segments_table(segments, units)}</div></section>',
        f'<section id="scores"><h2>Change scores</h2>{score_html}</section>',
        f'<section id="uncertainty"><h2>Uncertainty per source</h2><h3>Uncertainty stages and sensor profiles'
        f"</h3>{uncertainty_notes(provenance)}{sigma_html}</section>",
        f'<section id="provenance"><h2>Provenance of {esc(epoch)}</h2>{counts_tables(provenance, sets)}'
        f"<h3>Inputs</h3>{inputs_table(provenance)}<h3>Stages</h3>{stages_table(provenance)}"
        f"<h3>Run</h3>{run_facts(provenance)}</section>",
    ]
    data = {"view": figure, "segments": segment_boxes(segments, scene.centre),
            "histograms": [f for f in (score_fig, sigma_fig) if f is not None]}
    footer = ("Written by <code>gdt report</code> (gdt-pipeline). Self-contained: plotly.js and every figure's data "
              "are in this file; nothing is fetched when it is opened.")
    return PageParts(title=f"gdt report: {twin} at {epoch}", header=header, sections=sections, data=data,
                     footer=footer)
