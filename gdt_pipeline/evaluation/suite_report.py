"""The figures of ``gdt eval --suite`` over its scenes: per method the mean and the worst change F1, removal recall
by visible area and false removals by area; as a terminal table and as a markdown table for the docs."""

from __future__ import annotations

from typing import Any

import numpy as np

from .peer_runs import C2C_TAU

LABELS = {"gdt": "gdt (default workflow)", "c2c_fixed": f"C2C/C2M, τ {C2C_TAU * 100:g} cm",
          "c2c_best": "C2C/C2M, best τ*", "m3c2_default": "M3C2, defaults", "m3c2_best": "M3C2, best r and reg*",
          "m3c2ep": "M3C2-EP, 2,000 core points", "c2c_reverse": f"reverse C2C, τ {C2C_TAU * 100:g} cm (removal)"}
ORDER = tuple(LABELS)
COLUMNS = (("f1", "F1"), ("removal", "removal recall"), ("false", "false removals"))


def _stats(values: list[float | None], worst: str) -> dict[str, Any]:
    """Mean and worst (min or max) of the defined values, and how many scenes had one."""
    v = np.array([x for x in values if x is not None], dtype=np.float64)
    if not v.size:
        return {"mean": None, "worst": None, "n": 0}
    return {"mean": float(v.mean()), "worst": float(v.min() if worst == "min" else v.max()), "n": int(v.size)}


def summarise(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per method over the scenes: mean and worst change F1, removal recall by visible area (worst: lowest) and
    false removals by area (worst: highest); None where no scene defined the figure."""
    names = [n for n in ORDER if any(n in r["methods"] or n in ((r.get("removal") or {}).get("methods") or {})
                                     for r in rows)]
    out = {}
    for name in names:
        f1 = [r["methods"][name]["f1"] for r in rows if name in r["methods"]]
        rem = [((r.get("removal") or {}).get("methods") or {}).get(name) for r in rows]
        out[name] = {"label": LABELS[name], "f1": _stats(f1, "min") if f1 else None,
                     "removal": _stats([m["recall"] for m in rem if m], "min") if any(rem) else None,
                     "false": _stats([m["false_removals"] for m in rem if m], "max") if any(rem) else None}
    return out


def _cells(s: dict[str, Any] | None) -> tuple[str, str]:
    if not s or s["mean"] is None:
        return "–", "–"
    return f"{s['mean']:.4f}", f"{s['worst']:.4f}"


def format_suite_table(result: dict[str, Any]) -> str:
    """The summary as a plain-text table, with the run's time per scene."""
    rows = result["rows"]
    per_scene = np.mean([r["seconds"]["total"] for r in rows]) if rows else 0.0
    head = f"{'method':<32}" + "".join(f" {t + ' mean':>22} {'worst':>8}" for _, t in COLUMNS)
    lines = [f"suite {result['suite']!r}: {result['scenes']} scene(s), seed {result['seed']}, "
             f"{per_scene:.1f} s per scene ({result['out']})", head]
    for s in result["summary"].values():
        cells = "".join(f" {_cells(s[c])[0]:>22} {_cells(s[c])[1]:>8}" for c, _ in COLUMNS)
        lines.append(f"{s['label'][:32]:<32}{cells}")
    lines.append("worst: the lowest F1 and removal recall, the highest false-removal share of the scenes; "
                 "* tuned on each scene's truth: an upper bound no user has")
    lines.append(moved_line(rows))
    lines += [f"FAILED scene {f['scene']} (seed {f['seed']}): {f['error']}" for f in result.get("failed", [])]
    return "\n".join(lines)


def moved_line(rows: list[dict[str, Any]]) -> str:
    """How many moved parts the twin recorded as moved, the displacement errors, and records naming unmoved parts."""
    parts = [p for r in rows for p in (r.get("moved") or {}).get("parts", {}).values()]
    errors = [p["error_mm"] for p in parts if p["recorded"]]
    wrong = sum(len((r.get("moved") or {}).get("wrong_records", [])) for r in rows)
    text = f"moved parts recorded as moved: {len(errors)} of {len(parts)}"
    if errors:
        text += f", displacement error median {np.median(errors):.2f} mm, largest {max(errors):.2f} mm"
    return text + f"; moved records naming a part that did not move: {wrong}"


def suite_markdown(result: dict[str, Any]) -> str:
    """The summary as a markdown table (for docs/evaluation.md), with the command that reproduces it."""
    peers = ",".join(result["peers"]) or "none"
    lines = [f"`gdt eval --suite {result['suite']} --scenes {result['scenes']} --seed {result['seed']} "
             f"--peers {peers}`", "",
             "| method | F1 mean | F1 worst | removal recall mean | worst | false removals mean | worst |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, s in result["summary"].items():
        label = f"**{s['label']}**" if name == "gdt" else s["label"]
        lines.append(f"| {label} | " + " | ".join(" | ".join(_cells(s[c])) for c, _ in COLUMNS) + " |")
    lines.append("")
    lines.append("F1: change F1 of the scan's points (facets weighted by area for mesh scans); removal recall: share "
                 "of the visible area of removed and moved parts' CAD facets marked removed; false removals: share of "
                 "the visible area of unchanged parts marked removed; worst: lowest F1 and recall, highest false "
                 "removals over the scenes; * tuned on each scene's truth.")
    lines += ["", moved_line(result["rows"]) + "."]
    lines += [f"Failed: scene {f['scene']} (seed {f['seed']}): {f['error']}" for f in result.get("failed", [])]
    return "\n".join(lines) + "\n"
