"""What `gdt run` would refuse, `gdt validate` finds first: each case fails both commands alike, before anything runs,
with one located line (file:line:col: loc: message) and exit 1, and the run writes no twin."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from gdt_pipeline import StageSpec, hookimpl
from gdt_pipeline.errors import WorkflowError
from gdt_pipeline.plugins import load_registry
from gdt_pipeline.sensors import SensorProfile
from gdt_pipeline.workflow import load_workflow

from .conftest import CubeScene, make_cube_scene, run_gdt, write_cube_workflow

SCAN_SIGMA = "  - uses: constant\n    role: as-is\n    with: {model: isotropic, sigma: 0.002}\n"
IDENTITY = "  - uses: identity\n    role: as-is\n"
# nine levels of nine aliases: 9^10 nodes once expanded, from under 1 KB
BOMB = "l0: &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
    f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]\n" for i in range(1, 10))


@dataclass(frozen=True)
class Case:
    """A workflow mistake: how to make it (text edit, files to add) and what the one problem says where."""

    name: str
    edit: Callable[[str], str]
    loc: str
    says: tuple[str, ...]
    files: tuple[tuple[str, str], ...] = ()


def _profile_stage(ref: str, stage: str = "sensor_model") -> Callable[[str], str]:
    return lambda t: t.replace(SCAN_SIGMA, f"  - uses: {stage}\n    role: as-is\n    with: {{profile: {ref}, "
                                           f"viewpoint: [3, 0, 1]}}\n" if stage == "sensor_model" else
                               f"  - uses: {stage}\n    role: as-is\n    with: {{profile: {ref}}}\n")


def _profile(range_sigma: str, lateral_sigma: str = "[0.002, 0.0]") -> str:
    return f"name: p\nunits: m\nrange_sigma: {range_sigma}\nlateral_sigma: {lateral_sigma}\n"


CASES = [
    Case("alias bomb", lambda t: t + BOMB, "", ("too many nodes after alias expansion",)),
    Case("recursive alias", lambda t: t + "loop: &loop [1, *loop]\n", "", ("recursive structure",)),
    Case("infinite sigma", lambda t: t.replace("sigma: 0.002", "sigma: .inf"), "stages.2.with.sigma",
         ("finite number",)),
    Case("NaN viewpoint", lambda t: t.replace("name: scan}", "name: scan, viewpoints: [[0, .nan, 1]]}"),
         "epochs.1.inputs.0.viewpoints.0.1", ("finite number",)),
    Case("profile missing", _profile_stage("nowhere.yaml"), "stages.2.with.profile",
         ("no file", "nowhere.yaml")),
    Case("profile is a directory", _profile_stage("."), "stages.2.with.profile", ("is a directory, not a file",)),
    Case("profile not YAML", _profile_stage("broken.yaml"), "stages.2.with.profile",
         ("broken.yaml:2:1: YAML syntax error",),
         (("broken.yaml", "name: [unclosed\n"),)),
    Case("profile schema", _profile_stage("schema.yaml"), "stages.2.with.profile", ("range_sigma", "Field required"),
         (("schema.yaml", "name: p\nlateral_sigma: [0.002, 0]\n"),)),
    Case("profile negative sigma", _profile_stage("neg.yaml"), "stages.2.with.profile",
         ("range_sigma", "must be ≥ 0", "[1] = -0.001"), (("neg.yaml", _profile("[0.002, -0.001, 0.0]")),)),
    Case("profile infinite sigma", _profile_stage("inf.yaml"), "stages.2.with.profile",
         ("lateral_sigma.0", "finite number"), (("inf.yaml", _profile("[0.002, 0, 0]", "[.inf, 0]")),)),
    Case("profile all zero", _profile_stage("zero.yaml"), "stages.2.with.profile", ("at least one σ term > 0",),
         (("zero.yaml", _profile("[0, 0, 0]", "[0, 0]")),)),
    Case("calibrated needs isotropic", _profile_stage("tof_low_cost", "calibrated"), "stages.2.with.profile",
         ("not isotropic",)),
    Case("most_reliable without rov", lambda t: t.replace("uses: keep_unchanged", "uses: most_reliable"),
         "stages.6.uses", ("'most_reliable' needs a region-of-view stage", "sensor_frustum", "E1")),
    Case("replace_in_view without rov", lambda t: t.replace("uses: keep_unchanged", "uses: replace_in_view"),
         "stages.6.uses", ("'replace_in_view' needs a region-of-view stage", "sensor_frustum")),
    Case("input is a directory", lambda t: t.replace("path: scan.ply", "path: sub"), "epochs.1.inputs.0.path",
         ("is a directory, not a file",), (("sub/keep.txt", ""),)),
    Case("part file missing", lambda t: t.replace("uses: keep_unchanged", "uses: keep_unchanged\n    with: "
                                                  "{parts: [{name: bracket, path: bracket.obj}]}"),
         "stages.6.with.parts.0.path", ("part 'bracket'", "no model file")),
    Case("part file empty", lambda t: t.replace("uses: keep_unchanged", "uses: keep_unchanged\n    with: "
                                                "{parts: [{name: bracket, path: empty.obj}]}"),
         "stages.6.with.parts.0.path", ("empty (0 bytes)",), (("empty.obj", ""),)),
    Case("given file missing", lambda t: t.replace(IDENTITY, "  - uses: given\n    role: as-is\n    with: "
                                                   "{file: T.txt}\n"), "stages.1.with.file", ("not found",)),
    Case("given file not rigid", lambda t: t.replace(IDENTITY, "  - uses: given\n    role: as-is\n    with: "
                                                     "{file: T.txt}\n"), "stages.1.with.file",
         ("not a rigid 4x4", "not a rotation"), (("T.txt", "2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"),)),
    Case("given without a transform", lambda t: t.replace(IDENTITY, "  - uses: given\n    role: as-is\n"),
         "stages.1.with", ("exactly one of `transform` or `file`",)),
]


def _write(scene: CubeScene, case: Case) -> Path:
    wf = write_cube_workflow(scene)
    for name, text in case.files:
        (scene.dir / name).parent.mkdir(parents=True, exist_ok=True)
        (scene.dir / name).write_text(text)
    text = case.edit(wf.read_text())
    assert text != wf.read_text(), f"{case.name}: the edit changed nothing"
    bad = scene.dir / "bad.yaml"
    bad.write_text(text)
    return bad


def _assert_one_problem(lines: list[str], wf: Path, case: Case) -> None:
    assert len(lines) == 1, lines
    line = lines[0]
    assert re.match(rf"{re.escape(str(wf))}:\d+:\d+: ", line), line
    assert f": {case.loc}: " in line or not case.loc, line  # a YAML-level problem has a place but no key
    for frag in case.says:
        assert frag in line, (frag, line)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_validate_and_run_refuse_alike(tmp_path: Path, registry: Any, case: Case) -> None:
    scene = make_cube_scene(tmp_path / "scene", n_cube=400, n_new=100)
    wf = _write(scene, case)
    with pytest.raises(WorkflowError) as info:
        load_workflow(wf, registry)
    _assert_one_problem(info.value.problems, wf, case)
    res = run_gdt("validate", str(wf))
    assert res.returncode == 1, res.stdout + res.stderr
    _assert_one_problem([ln for ln in res.stdout.splitlines() if ln.strip()], wf, case)
    res = run_gdt("run", "-q", str(wf))
    assert res.returncode == 1, res.stdout + res.stderr
    assert case.says[0] in res.stdout + res.stderr
    assert not (scene.dir / "twin").exists()


def test_the_valid_workflow_still_validates(tmp_path: Path, registry: Any) -> None:
    wf = write_cube_workflow(make_cube_scene(tmp_path / "scene", n_cube=400, n_new=100))
    assert load_workflow(wf, registry).model.stages[2].with_.sigma == 0.002


def test_a_valid_profile_file_validates(tmp_path: Path, registry: Any) -> None:
    scene = make_cube_scene(tmp_path / "scene", n_cube=400, n_new=100)
    (scene.dir / "ok.yaml").write_text(_profile("[0.002, 0.0, 0.0]", "[0.002, 0.0]"))
    wf = _write(scene, Case("ok", _profile_stage("ok.yaml", "calibrated"), "", ()))
    load_workflow(wf, registry)


def test_profile_signs_are_checked_in_the_model() -> None:
    with pytest.raises(ValueError, match=r"range_sigma[\s\S]*\[0\] = -0.01"):
        SensorProfile(name="x", range_sigma=[-0.01, 0, 0], lateral_sigma=[0.01, 0])
    assert SensorProfile(name="x", range_sigma=[0.01, 0, 0], lateral_sigma=[0, 0]).range_sigma[0] == 0.01


class _Raising:
    """A third-party stage whose `validate` hook itself fails: a problem of its entry, not an internal error."""

    @staticmethod
    @hookimpl
    def gdt_stages() -> list[StageSpec]:
        """One fusion whose check of its params raises."""
        from stages.fusion import KeepUnchangedParams

        def boom(params: Any, base: Path) -> list[tuple[str, str]]:
            raise RuntimeError("cannot check")

        return [StageSpec(name="fragile_fusion", family="fusion", version="1", params=KeepUnchangedParams,
                          run=lambda ctx: {}, requires=("recent",), optional=("change",), provides=("composite",),
                          validate=boom)]


def test_a_failing_validate_hook_is_a_problem_of_its_entry(tmp_path: Path) -> None:
    reg = load_registry(blocked=(), extra=[("fragile", _Raising)])
    scene = make_cube_scene(tmp_path / "scene", n_cube=400, n_new=100)
    wf = _write(scene, Case("x", lambda t: t.replace("uses: keep_unchanged", "uses: fragile_fusion"), "", ()))
    with pytest.raises(WorkflowError) as info:
        load_workflow(wf, reg)
    [problem] = info.value.problems
    assert "stages.6.with: stage 'fragile_fusion'" in problem and "RuntimeError: cannot check" in problem
