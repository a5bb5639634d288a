"""The report's HTML tables: counts per change state and per element set, the segments, and the provenance (inputs,
stages, uncertainty stages and sensor profiles, packages). Every value from the twin is HTML-escaped."""

from __future__ import annotations

import html
import json
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from twin_store import STATE_NAMES

from ..types import Segment
from .scene import SetCensus


def esc(value: Any) -> str:
    """A value as escaped HTML text."""
    return html.escape(str(value), quote=True)


def compact_json(value: Any) -> str:
    """A value as one line of JSON, keys sorted (params and reports in the stage table)."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, default=str)


def num(value: Any, spec: str = ".4g") -> str:
    """A number for a table cell ("–" for None or NaN)."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "–"
    return format(value, spec)


def table(headers: Sequence[str], rows: Iterable[Sequence[str]], *, table_id: str | None = None,
          row_attrs: Sequence[str] | None = None, numeric: Sequence[int] = ()) -> str:
    """An HTML table; ``rows`` are cells already in HTML, ``row_attrs`` extra attributes per row, ``numeric`` the
    columns aligned right."""
    head = "".join(f'<th{" class=num" if i in numeric else ""}>{esc(h)}</th>' for i, h in enumerate(headers))
    body = []
    for k, cells in enumerate(rows):
        attrs = f" {row_attrs[k]}" if row_attrs else ""
        tds = "".join(f'<td{" class=num" if i in numeric else ""}>{c}</td>' for i, c in enumerate(cells))
        body.append(f"<tr{attrs}>{tds}</tr>")
    ident = f' id="{esc(table_id)}"' if table_id else ""
    return f"<table{ident}><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def counts_tables(provenance: dict[str, Any], sets: list[SetCensus]) -> str:
    """Elements per change state as the epoch recorded them, and per element set what it holds and shows."""
    counts = provenance.get("counts") or {}
    recorded = table(["state", "elements"], [[esc(n.replace("_", " ")), f"{int(counts.get(n, 0)):,}"]
                                             for n in STATE_NAMES], numeric=(1,)) if counts else \
        "<p>The epoch recorded no counts.</p>"
    rows = [[f"<code>{esc(s.key)}</code>", esc(s.kind), f"{s.elements:,}", f"{s.visible:,}", f"{s.shown:,}",
             *(f"{c:,}" for c in s.by_state), "yes" if s.new_here else "", "preview" if s.preview else ""]
            for s in sets]
    per_set = table(["element set", "kind", "elements", "visible", "in the view", *(n.replace("_", " ")
                    for n in STATE_NAMES), "new here", "payload"], rows, numeric=tuple(range(2, 8)))
    return (f"<h3>Elements per change state (recorded with the epoch)</h3>{recorded}"
            f"<details><summary>Per element set ({len(sets)}): visible elements per state; removed: hidden by this "
            f"epoch</summary>{per_set}</details>")


def _xyz(values: Any) -> str:
    return ", ".join(num(float(v)) for v in np.asarray(values, dtype=np.float64))


def segments_table(segments: list[Segment], units: str) -> str:
    """One row per segment (``data-segment`` = its id); a click frames it in the 3-D view."""
    if not segments:
        return '<table id="segments"><tbody><tr><td>This epoch recorded no segments.</td></tr></tbody></table>'
    rows, attrs = [], []
    for seg in segments:
        part = "–"
        if seg.part is not None:
            part = f"{esc(seg.part)} (RMS {num(seg.fit_rms)} {esc(units)})"
        moved = "–"
        if seg.moved_item and seg.displacement is not None:
            d = np.asarray(seg.displacement, dtype=np.float64)
            moved = (f"{esc(seg.moved_item)}: {num(float(np.linalg.norm(d)))} {esc(units)} ({_xyz(d)}), "
                     f"{num(seg.rotation_deg, '.3g')}°, from segment {esc(seg.moved_from)}")
        rows.append([esc(seg.id), esc(seg.kind), _xyz(seg.centroid), f"{int(seg.size):,}",
                     num(seg.mean_score), "yes" if seg.artefact else "", part, moved])
        attrs.append(f'data-segment="{int(seg.id)}" class="segment {esc(seg.kind)}" tabindex="0"')
    return table(["id", "kind", f"centroid ({units})", "elements", "mean score", "artefact", "fitted part",
                  "moved (displacement, rotation)"], rows, table_id="segments", row_attrs=attrs, numeric=(0, 3, 4))


def _poses(inp: dict[str, Any]) -> str:
    parts = []
    for ds in inp.get("datasets") or []:
        pose = ds.get("pose") or {}
        where = f"{esc(pose.get('source', '–'))}" + (f" ({esc(pose['origin'])})" if pose.get("origin") else "")
        parts.append(f"<code>{esc(ds.get('name'))}</code>: {where}")
    return "<br>".join(parts) or "–"


def inputs_table(provenance: dict[str, Any]) -> str:
    """The epoch's input files: path, sha256, reader, elements, units and the station source per dataset."""
    rows = []
    for inp in provenance.get("inputs", []):
        sha = str(inp.get("sha256", ""))
        rows.append([f"<code>{esc(inp.get('path'))}</code>", f'<code title="{esc(sha)}">{esc(sha[:16])}…</code>',
                     esc(inp.get("reader") or "–"), f"{int(inp.get('elements') or 0):,}",
                     f"{esc(inp.get('units', '?'))} ×{num(inp.get('scale', 1.0))}", _poses(inp)])
    return table(["path", "sha256", "reader", "elements", "units, scale", "pose source per dataset"], rows,
                 numeric=(3,))


def stages_table(provenance: dict[str, Any]) -> str:
    """Every stage of the epoch: index, name, family, plugin and versions, params, report, seconds."""
    rows = []
    for st in provenance.get("stages", []):
        report = st.get("report") or {}
        shown = f"<details><summary>report</summary><code>{esc(compact_json(report))}</code></details>" \
            if report else ""
        rows.append([esc(st.get("index")), f"<b>{esc(st.get('uses'))}</b>", esc(st.get("family", "")),
                     f"{esc(st.get('plugin', ''))} {esc(st.get('plugin_version', ''))}", esc(st.get("version", "")),
                     f"<code>{esc(compact_json(st.get('params') or {}))}</code>{shown}", num(st.get("seconds"), ".3g")])
    return table(["#", "stage", "family", "plugin", "version", "params", "seconds"], rows, numeric=(0, 6))


def uncertainty_notes(provenance: dict[str, Any]) -> str:
    """The epoch's uncertainty stages: the model or sensor profile each used, the datasets it applied to, and what
    it recorded (a fitted profile, where one was)."""
    items = []
    for st in provenance.get("stages", []):
        if st.get("family") != "uncertainty":
            continue
        params = st.get("params") or {}
        profile = params.get("profile")
        what = f"sensor profile <b>{esc(profile)}</b>" if profile else \
            f"model <b>{esc(params.get('model', st.get('uses')))}</b>"
        applied = params.get("datasets") or "all datasets"
        fitted = st.get("report") or {}
        recorded = f"; recorded: <code>{esc(compact_json(fitted))}</code>" if fitted else ""
        items.append(f"<li>stage {esc(st.get('index'))} <b>{esc(st.get('uses'))}</b> ({esc(st.get('plugin'))} "
                     f"{esc(st.get('version'))}): {what}, on {esc(applied)}; params "
                     f"<code>{esc(compact_json(params))}</code>{recorded}</li>")
    return f"<ul>{''.join(items)}</ul>" if items else "<p>No uncertainty stage ran in this epoch.</p>"


def run_facts(provenance: dict[str, Any]) -> str:
    """Workflow, seed, times, Python and package versions of the epoch's run."""
    wf = provenance.get("workflow") or {}
    facts = [("workflow", f"{esc(wf.get('name', '?'))} (<code>{esc(wf.get('path', '?'))}</code>, sha256 "
                          f"<code>{esc(str(wf.get('sha256', ''))[:16])}…</code>)"),
             ("seed", esc(provenance.get("seed", "?"))), ("started", esc(provenance.get("started", "?"))),
             ("finished", esc(provenance.get("finished", "?"))),
             ("gdt-pipeline", esc(provenance.get("gdt_pipeline", "?"))), ("python", esc(provenance.get("python", "?"))),
             ("epoch key", f"<code>{esc(str(provenance.get('epoch_key') or '–')[:16])}</code>")]
    packages = ", ".join(f"{esc(k)} {esc(v)}" for k, v in sorted((provenance.get("packages") or {}).items()))
    facts.append(("packages", packages or "–"))
    return "<dl class=facts>" + "".join(f"<dt>{k}</dt><dd>{v}</dd>" for k, v in facts) + "</dl>"
