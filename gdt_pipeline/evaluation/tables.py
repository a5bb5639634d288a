"""The evaluation result as a plain-text table, for the terminal."""

from __future__ import annotations

from typing import Any


def format_table(result: dict[str, Any]) -> str:
    """The results as a plain-text table."""
    def f(x: Any, spec: str = ".4f") -> str:
        return "–" if x is None else format(x, spec)

    lines = [f"{result['workflow']} -> {result['twin']}",
             f"{'epoch':<6} {'points':>8} {'changed':>8}  {'method':<40} {'prec.':>7} {'recall':>7} {'F1':>7} "
             f"{'FA rate':>8} {'s':>7}"]
    for row in result["epochs"]:
        if not row.get("methods"):
            lines.append(f"{row['epoch']:<6} no ground truth ({'; '.join(row['missing_truth'])})")
            continue
        for i, m in enumerate(row["methods"]):
            head = f"{row['epoch']:<6} {row['points']:>8} {row['changed']:>8}" if i == 0 else " " * 24
            pts = "" if m["evaluated_points"] == row["points"] else f" [{m['evaluated_points']} pts]"
            lines.append(f"{head}  {(m['label'] + pts)[:40]:<40} {f(m['precision']):>7} {f(m['recall']):>7} "
                         f"{f(m['f1']):>7} {f(m['false_alarm_rate']):>8} {f(m['seconds'], '.1f'):>7}")
        rem = row.get("removal")
        if rem and "methods" in rem:
            for label, r in rem["methods"].items():
                lines.append(f"{'':24}  removal {label:<12} recall {f(r['recall'])} (of {rem['removed_in_view']} "
                             f"visible removed facets), false removals on occluded "
                             f"{f(r['false_removal_rate_occluded'])} (of {rem['occluded_facets']})")
        for name, per in (rem or {}).get("objects", {}).items():
            found = ", ".join(f"{k}: {'found' if v['found'] else 'missed'} ({v['marked']}/{v['facets_seen']} visible "
                              f"facets)" for k, v in per.items())
            lines.append(f"{'':24}  removed {name}: {found}")
        for o in row.get("objects", []):
            if o["truth"] != "new" or "methods" not in o:
                continue
            found = ", ".join(f"{k}: {'found' if v['found'] else 'missed'}"
                              + (f" {v['centre_error_mm']:.2f} mm" if v["found"] else "")
                              for k, v in o["methods"].items())
            solid = (f"; segment centroid to the part's solid centre {o['segment_to_solid_centre_mm']:.1f} mm"
                     if o.get("segment_to_solid_centre_mm") is not None else "")
            if o.get("fitted_part") is not None:
                solid += (f"; fitted {o['fitted_part']!r} centre to the solid centre "
                          f"{o['fitted_centre_to_solid_centre_mm']:.2f} mm")
            elif o.get("segment_to_solid_centre_mm") is not None:
                solid += "; no part fitted"
            lines.append(f"{'':24}  new {o['name']} ({o['points']} pts): {found}{solid}")
        if row.get("segments"):
            g = row["segments"]
            lines.append(f"{'':24}  twin segments: {g['new_segments']} new, {g['removed_segments']} removed, "
                         f"{g['artefacts']} artefacts; removed objects as removed segments: {g['removed_found']}")
        if row.get("composite"):
            c = row["composite"]
            lines.append(f"{'':24}  composite to true as-is geometry: mean {c['mean_mm']:.2f} mm, "
                         f"p95 {c['p95_mm']:.2f} mm")
    lines.append("* best threshold of a sweep on the truth: an upper bound no user has; FA rate: flagged share of "
                 "unchanged points")
    return "\n".join(lines)
