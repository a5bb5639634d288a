"""The ``gdt eval`` report: markdown tables, the result as JSON, and plots (F1 per method, distance histograms,
a top-down change map per epoch), drawn with matplotlib's Agg canvas (no display, no global pyplot state)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

MAP_POINTS = 50_000  # points drawn per change-map panel (seeded subsample): readable and fast
COLOURS = {"tp": "#2ca02c", "fp": "#d62728", "fn": "#ff7f0e", "tn": "#d9d9d9"}


def _f(x: Any, spec: str = ".4g") -> str:
    return "–" if x is None else format(x, spec)


def format_markdown_table(result: dict[str, Any]) -> str:
    """Per epoch, one markdown table row per method."""
    lines = []
    for row in result["epochs"]:
        if not row.get("methods"):
            lines.append(f"**{row['epoch']}**: no ground truth\n")
            continue
        lines.append(f"**{row['epoch']}**: {row['points']} scan points, {row['changed']} on changed geometry\n")
        lines.append("| method | kind | precision | recall | F1 | false-alarm rate | false alarms | points | s |")
        lines.append("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for m in row["methods"]:
            lines.append(f"| {m['label']} | {m['kind']} | {_f(m['precision'])} | {_f(m['recall'])} | {_f(m['f1'])} | "
                         f"{_f(m['false_alarm_rate'])} | {m['fp']} | {m['evaluated_points']} | "
                         f"{_f(m['seconds'], '.3g')} |")
        lines.append("")
    lines.append("\\* a threshold chosen on the ground truth: an upper bound no user has.")
    return "\n".join(lines)


def _canvas(w: float, h: float) -> tuple[Any, Any]:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100)
    FigureCanvasAgg(fig)
    return fig, fig.canvas


def _plot_scores(result: dict[str, Any], path: Path) -> None:
    fig, _ = _canvas(8, 4)
    ax_f1, ax_fa = fig.subplots(1, 2)
    names: list[str] = []
    for row in result["epochs"]:
        for m in row.get("methods", []):
            if m["name"] not in names:
                names.append(m["name"])
    epochs = [r for r in result["epochs"] if r.get("methods")]
    width = 0.8 / max(len(names), 1)
    for k, name in enumerate(names):
        f1 = [next((m["f1"] for m in r["methods"] if m["name"] == name), None) for r in epochs]
        fa = [next((m["false_alarm_rate"] for m in r["methods"] if m["name"] == name), None) for r in epochs]
        x = np.arange(len(epochs)) + k * width
        ax_f1.bar(x, [np.nan if v is None else v for v in f1], width, label=name)
        ax_fa.bar(x, [np.nan if v is None else v for v in fa], width, label=name)
    for ax, title in ((ax_f1, "F1 of changed points (none: no true change)"), (ax_fa, "false-alarm rate")):
        ax.set_xticks(np.arange(len(epochs)) + 0.4 - width / 2, [r["epoch"] for r in epochs])
        ax.set_title(title, fontsize=9)
        ax.set_ylim(0, 1.05)
    ax_fa.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)


def _plot_hist(epoch: str, arr: dict[str, Any], path: Path) -> bool:
    shown = [(n, m) for n, m in arr["methods"].items() if m.get("distance") is not None and m.get("index") is None
             and not n.endswith("_best")]
    if not shown:
        return False
    fig, _ = _canvas(4 * len(shown), 3.5)
    axes = np.atleast_1d(fig.subplots(1, len(shown)))
    truth = arr["truth"]
    for ax, (name, m) in zip(axes, shown, strict=True):
        d = np.abs(np.asarray(m["distance"], dtype=float)) * 1000.0
        ok = np.isfinite(d) & (d > 0)
        if not ok.any():
            continue
        bins = np.geomspace(max(d[ok].min(), 1e-4), d[ok].max() * 1.01, 60)
        ax.hist(d[ok & ~truth], bins=bins, color="#7f7f7f", alpha=0.7, label="unchanged")
        ax.hist(d[ok & truth], bins=bins, color="#d62728", alpha=0.7, label="changed")
        ax.set_xscale("log")
        ax.set_xlabel("|distance| (mm)")
        ax.set_title(f"{epoch}: {name} ({int((~np.isfinite(d)).sum())} without counterpart)", fontsize=8)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    return True


def _plot_map(epoch: str, arr: dict[str, Any], path: Path) -> None:
    pts, truth = arr["points"], arr["truth"]
    rng = np.random.default_rng(0)
    pick = np.sort(rng.choice(len(pts), size=min(MAP_POINTS, len(pts)), replace=False))
    panels = [("truth", truth, None)] + [(n, m["changed"], m.get("index")) for n, m in arr["methods"].items()
                                         if m.get("changed") is not None]
    cols = min(len(panels), 4)
    rows = int(np.ceil(len(panels) / cols))
    fig, _ = _canvas(3.2 * cols, 3.2 * rows)
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    # a top-down view of the plane the points spread most in
    spread = np.argsort(np.ptp(pts, axis=0))[::-1][:2]
    for ax, (name, mask, index) in zip(axes, panels, strict=False):
        if index is None:
            sel, p, t = pick, np.asarray(mask, bool)[pick], truth[pick]
        else:
            sel, p, t = np.asarray(index), np.asarray(mask, bool), truth[np.asarray(index)]
        colour = np.where(p & t, COLOURS["tp"], np.where(p & ~t, COLOURS["fp"],
                                                         np.where(~p & t, COLOURS["fn"], COLOURS["tn"])))
        if name == "truth":
            colour = np.where(t, "#d62728", COLOURS["tn"])
        order = np.argsort(colour != COLOURS["tn"])  # changed on top of unchanged
        ax.scatter(pts[sel][order, spread[0]], pts[sel][order, spread[1]], c=colour[order], s=0.5, linewidths=0,
                   rasterized=True)
        ax.set_title(name, fontsize=8)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=6)
    for ax in axes[len(panels):]:
        ax.set_axis_off()
    fig.suptitle(f"{epoch}: green hit, red false alarm, orange missed", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)


def write_report(result: dict[str, Any], arrays: dict[str, Any], out_dir: Path) -> Path:
    """Write report.md, result.json and the plots into ``out_dir``; return the path of report.md."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "result.json").write_text(json.dumps(result, indent=2, default=float) + "\n", encoding="utf-8")
    md = [f"# Evaluation of `{Path(result['workflow']).name}`", "",
          f"- workflow: `{result['workflow']}`", f"- twin: `{result['twin']}`",
          f"- scene: {result.get('scene') or '–'}, seed {result.get('seed')}",
          f"- evaluation time: {_f(result.get('seconds'), '.1f')} s", "", format_markdown_table(result), ""]
    _plot_scores(result, out_dir / "f1.png")
    md += ["![F1 and false alarms per method](f1.png)", ""]
    for row in result["epochs"]:
        eid = row["epoch"]
        rem = row.get("removal")
        if rem and "methods" in rem:
            md += [f"## {eid}: removed geometry", "", "| method | recall (visible removed facets) | "
                   "false removals, occluded | false removals, seen |", "| --- | --- | --- | --- |"]
            for label, r in rem["methods"].items():
                md.append(f"| {label} | {_f(r['recall'])} | {_f(r['false_removal_rate_occluded'])} | "
                          f"{_f(r['false_removal_rate_seen'])} |")
            for name, per in rem.get("objects", {}).items():
                md.append("")
                md.append(f"removed {name}: " + ", ".join(
                    f"{k} {'found' if v['found'] else 'missed'} ({v['marked']}/{v['facets_seen']} visible facets)"
                    for k, v in per.items()))
            md += ["", rem.get("note", ""), ""]
        objects = [o for o in row.get("objects", []) if o.get("methods")]
        if objects:
            names = list(objects[0]["methods"])
            md += [f"## {eid}: new objects", "", "| object | points | " + " | ".join(names) + " |",
                   "| --- | --- | " + " | ".join("---" for _ in names) + " |"]
            for o in objects:
                cells = [("found, " + _f(v["centre_error_mm"], ".2f") + " mm") if v["found"] else "missed"
                         for v in (o["methods"].get(n, {"found": False}) for n in names)]
                md.append(f"| {o['name']} | {o['points']} | " + " | ".join(cells) + " |")
            found = {n: sum(bool(o["methods"].get(n, {}).get("found")) for o in objects) for n in names}
            md += ["", "found: " + ", ".join(f"{n} {k}/{len(objects)}" for n, k in found.items()),
                   "(centre error: found cluster's centroid to the noise-free centroid of the object's scanned "
                   "surface)", ""]
        if row.get("composite"):
            c = row["composite"]
            md += [f"{eid}: composite to the true as-is geometry: mean {c['mean_mm']:.3g} mm, 95th percentile "
                   f"{c['p95_mm']:.3g} mm ({c['n']} points).", ""]
        if eid in arrays:
            if _plot_hist(eid, arrays[eid], out_dir / f"hist_{eid}.png"):
                md += [f"![distance histograms {eid}](hist_{eid}.png)", ""]
            _plot_map(eid, arrays[eid], out_dir / f"map_{eid}.png")
            md += [f"![change map {eid}](map_{eid}.png)", ""]
        for note in row.get("notes", []):
            md.append(f"- {note}")
        md.append("")
    path = out_dir / "report.md"
    path.write_text("\n".join(md).rstrip() + "\n", encoding="utf-8")
    return path
