"""The gdt command as a user meets it: help everywhere, version, structured log, progress output."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from gdt_pipeline import __version__

from .conftest import CubeScene, run_gdt, write_cube_workflow


@pytest.mark.parametrize("cmd", [[], ["run"], ["validate"], ["plugins"], ["schema"], ["scene"]])
def test_help_everywhere(cmd: list[str]) -> None:
    res = run_gdt(*cmd, "--help")
    assert res.returncode == 0 and "Usage: gdt" in res.stdout and len(res.stdout.splitlines()) > 4


def test_version() -> None:
    res = run_gdt("--version")
    assert res.returncode == 0 and __version__ in res.stdout


def test_run_writes_structured_log_and_progress(cube_scene: CubeScene) -> None:
    wf = write_cube_workflow(cube_scene)
    log = cube_scene.dir / "run.jsonl"
    res = run_gdt("run", str(wf), "--log-file", str(log))
    assert res.returncode == 0, res.stderr
    assert "epoch E1 (2/2, as-is, 1 input)" in res.stderr and "bhattacharyya" in res.stderr
    assert "twin written to" in res.stdout
    events = [json.loads(line) for line in log.read_text().splitlines()]
    done = [e for e in events if e["message"] == "stage done"]
    assert [(e["epoch"], e["stage"]) for e in done][:3] == [("E0", "constant"), ("E0", "keep_unchanged"),
                                                            ("E1", "identity")]
    assert all(len(e["cache_key"]) == 64 and e["seconds"] >= 0 for e in done)
    lock = json.loads((cube_scene.dir / "twin" / "gdt.lock").read_text())
    assert [s["cache_key"] for s in lock["epochs"][1]["stages"]] == [e["cache_key"] for e in done[2:]]


def test_usage_errors_exit_non_zero(tmp_path: Path) -> None:
    res = run_gdt("run")
    assert res.returncode == 2 and "Missing argument" in res.stderr
    log = tmp_path / "no-such-folder" / "run.jsonl"
    res = run_gdt("run", "/nonexistent/wf.yaml", "--log-file", str(log))
    assert res.returncode == 2 and "'--log-file'" in res.stderr and str(log) in res.stderr, res.stderr
    assert "No such file or directory" in res.stderr and "internal error" not in res.stderr
    res = run_gdt("validate", "/nonexistent/wf.yaml")
    assert res.returncode == 1 and "workflow file not found" in res.stdout
