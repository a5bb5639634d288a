"""The screen `gdt run` ends with: per epoch what changed (elements by state, segments), what a registrar found (the
transform, its σ, fitness, overlap and warnings), where the time went (seconds per stage), and where the report is;
read back from the twin that was written, so it says what the twin holds."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

from rich.console import Group
from rich.table import Table

from ..types import Segment

STATE_COLUMNS = (("new", "new"), ("removed", "removed"), ("unchanged", "unchanged"), ("outside_rov", "outside view"),
                 ("not_comparable", "not comparable"))


def _segment_text(segments: list[Segment]) -> str:
    """Segments of an epoch in one cell: '2 new, 1 removed (1 artefact), 1 moved part'."""
    if not segments:
        return "-"
    new = sum(1 for s in segments if s.kind == "new")
    removed = sum(1 for s in segments if s.kind == "removed")
    artefacts = sum(1 for s in segments if s.artefact)
    moved = sum(1 for s in segments if s.moved_item)
    text = f"{new} new, {removed} removed"
    if artefacts:
        text += f" ({artefacts} artefact{'s' if artefacts != 1 else ''})"
    if moved:
        text += f", {moved} moved part{'s' if moved != 1 else ''}"
    return text


def change_table(store: Any) -> Table:
    """One row per epoch: elements by change state, segments, seconds."""
    table = Table(title="what changed", title_justify="left")
    table.add_column("epoch")
    for _, label in STATE_COLUMNS:
        table.add_column(label, justify="right")
    table.add_column("segments")
    table.add_column("seconds", justify="right")
    for eid in store.epochs():
        prov = store.provenance(eid)
        counts = prov.get("counts") or {}
        seconds = sum(float(st.get("seconds") or 0.0) for st in prov.get("stages", []))
        table.add_row(eid, *(f"{counts.get(key, 0):,}" for key, _ in STATE_COLUMNS),
                      _segment_text(store.read_segments(eid, members=False)), f"{seconds:.1f}")
    return table


def stage_table(store: Any) -> Table:
    """Seconds per stage, summed over the epochs it ran in, slowest first."""
    seconds: dict[tuple[str, str], float] = defaultdict(float)
    runs: dict[tuple[str, str], int] = defaultdict(int)
    for eid in store.epochs():
        for st in store.provenance(eid).get("stages", []):
            key = (str(st.get("family", "")), str(st.get("uses", "")))
            seconds[key] += float(st.get("seconds") or 0.0)
            runs[key] += 1
    table = Table(title="time per stage", title_justify="left")
    for name, justify in (("stage", "left"), ("family", "left"), ("epochs", "right"), ("seconds", "right")):
        table.add_column(name, justify=justify)
    for (family, name), total in sorted(seconds.items(), key=lambda kv: -kv[1]):
        table.add_row(name, family, str(runs[(family, name)]), f"{total:.2f}")
    return table


def _xyz(values: Any, digits: int) -> str:
    return "(" + ", ".join(f"{float(v):.{digits}f}" for v in values) + ")" if values else "-"


def registration_table(store: Any) -> Table | None:
    """One row per epoch a registrar fitted: the transform (rotation, shift at the data's centre) with its σ, the
    fitness and overlap, and what it warned of; None when no epoch was registered by a fit."""
    table = Table(title="registration", title_justify="left")
    for name, justify in (("epoch", "left"), ("method", "left"), ("rotation °", "right"), ("σ rotation °", "right"),
                          ("shift at centre", "right"), ("σ shift", "right"), ("fitness", "right"),
                          ("overlap", "right"), ("warnings", "left")):
        table.add_column(name, justify=justify)
    for eid in store.epochs():
        prov = store.provenance(eid)
        reg = prov.get("registration") or {}
        rep = next((st.get("report") or {} for st in prov.get("stages", []) if st.get("family") == "registrar"), {})
        if "rotation_deg" not in rep:
            continue  # identity, given, or no registrar: nothing was fitted
        table.add_row(eid, str(reg.get("method", "")), f"{rep['rotation_deg']:.4f}",
                      _xyz(rep.get("sigma_rotation_deg"), 4), _xyz(rep.get("shift_at_center"), 3),
                      _xyz(rep.get("sigma_translation"), 3), f"{float(rep.get('fitness', 0.0)):.3f}",
                      f"{float(rep.get('overlap', float('nan'))):.3f}", "; ".join(rep.get("warnings") or []) or "-")
    return table if table.row_count else None


def run_summary(twin: Path) -> Group:
    """The end-of-run screen for the twin at ``twin``: what changed per epoch, the registrations, and the time per
    stage."""
    from twin_store import TwinStore

    store = TwinStore.open(twin)
    reg = registration_table(store)
    return Group(change_table(store), *([reg] if reg is not None else []), stage_table(store))
