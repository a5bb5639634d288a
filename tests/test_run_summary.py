"""`gdt run` ends with one screen read back from the twin: elements per change state and segments per epoch, and the
seconds per stage."""

from __future__ import annotations

import re
from pathlib import Path

from twin_store import TwinStore

from .conftest import make_cube_scene, run_gdt, write_cube_workflow


def test_run_ends_with_what_changed_and_where_the_time_went(tmp_path: Path) -> None:
    scene = make_cube_scene(tmp_path / "cube")
    workflow = write_cube_workflow(scene)
    res = run_gdt("run", str(workflow), "-q", "--no-report")
    assert res.returncode == 0, res.stderr
    store = TwinStore.open(scene.dir / "twin")
    counts = store.provenance("E1")["counts"]
    row = next(line for line in res.stdout.splitlines() if line.startswith("│ E1 "))
    cells = [c.strip() for c in row.strip("│").split("│")]
    assert cells[:6] == ["E1", f"{counts['new']:,}", f"{counts['removed']:,}", f"{counts['unchanged']:,}",
                         f"{counts['outside_rov']:,}", f"{counts['not_comparable']:,}"]
    segments = store.read_segments("E1")
    assert cells[6].startswith(f"{sum(s.kind == 'new' for s in segments)} new") and counts["new"] > 900
    stages = {st["uses"] for e in store.epochs() for st in store.provenance(e)["stages"]}
    listed = set(re.findall(r"^│ (\w+) +│ \w+ +│ +\d+ │", res.stdout, flags=re.MULTILINE))
    assert listed == stages and "time per stage" in res.stdout
    assert "report:" not in res.stdout


def test_run_writes_the_report_beside_the_twin_by_default(tmp_path: Path) -> None:
    scene = make_cube_scene(tmp_path / "cube")
    res = run_gdt("run", str(write_cube_workflow(scene)), "-q")
    assert res.returncode == 0, res.stderr
    report = scene.dir / "twin_report.html"
    assert f"report: {report} (" in res.stdout and "points shown" in res.stdout
    assert report.stat().st_size > 1e6 and "gdtReportReady" in report.read_text(encoding="utf-8")
