"""`gdt validate`: every problem at once, each as file:line:col: loc: message, with "did you mean"."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from gdt_pipeline.errors import WorkflowError
from gdt_pipeline.workflow import json_schema, load_workflow

from .conftest import REPO, make_cube_scene, run_gdt, write_cube_workflow

LINE_RE = re.compile(r"^(?P<file>.+?):(?P<line>\d+):(?P<col>\d+): (?P<loc>[\w.()]+): (?P<msg>.+)$")

THREE_MISTAKES = """\
name: three-mistakes
twin: out
epochs:
  - id: E0
    role: as-designed
    inputs: [{path: cad.obj}]
  - id: E1
    role: as-is
    inputs: [{path: scan.ply}]
stages:
  - uses: constant
    with: {model: isotropic, sigma: 0.01}
  - uses: bhattacharya
    role: as-is
  - uses: fixed
    role: as-is
    with: {tau: 3, threshhold: 2}
  - uses: keep_unchanged
"""


def _problems(path: Path, registry) -> list[str]:
    with pytest.raises(WorkflowError) as info:
        load_workflow(path, registry)
    return info.value.problems


def test_three_mistakes_three_errors_with_positions(tmp_path: Path) -> None:
    scene = make_cube_scene(tmp_path)
    wf = tmp_path / "bad.yaml"
    wf.write_text(THREE_MISTAKES)
    res = run_gdt("validate", str(wf))
    assert res.returncode != 0
    lines = [ln for ln in res.stdout.splitlines() if ln.strip()]
    assert len(lines) == 3, res.stdout
    parsed = [LINE_RE.match(ln) for ln in lines]
    assert all(parsed), lines
    found = [(m["loc"], int(m["line"]), int(m["col"]), m["msg"]) for m in parsed]
    assert all(Path(m["file"]) == wf for m in parsed)
    # the unknown stage: at the value of `uses:` on line 13, with a suggestion
    [msg] = [m for loc, line, col, m in found if (loc, line, col) == ("stages.1.uses", 13, 11) and "unknown" in m]
    assert "unknown stage 'bhattacharya'" in msg and "did you mean 'bhattacharyya'" in msg
    # the misspelt parameter: at its key on line 17
    [msg] = [m for loc, line, col, m in found if (loc, line, col) == ("stages.2.with.threshhold", 17, 20)]
    assert "unknown parameter 'threshhold' of stage 'fixed'" in msg and "tau" in msg
    # the slot nobody provides: correspondences, needed by the (misspelt) distance stage at E1
    slot = [m for *_, m in found if "requires slot" in m]
    assert len(slot) == 1 and "'correspondences'" in slot[0] and "E1" in slot[0] and "nearest" in slot[0]
    assert scene.cad.exists()


def test_reference_at_first_epoch_gets_a_hint(tmp_path: Path, registry) -> None:
    scene = make_cube_scene(tmp_path)
    wf = write_cube_workflow(scene)
    wf.write_text(wf.read_text().replace("  - uses: nearest\n    role: as-is\n", "  - uses: nearest\n"))
    problems = _problems(wf, registry)
    assert len(problems) == 1
    assert "requires slot 'reference'" in problems[0] and "at epoch E0" in problems[0]
    assert "role: as-is" in problems[0]


def test_missing_fusion_and_bad_values(tmp_path: Path, registry) -> None:
    scene = make_cube_scene(tmp_path)
    wf = write_cube_workflow(scene)
    text = wf.read_text().replace("  - uses: keep_unchanged\n", "").replace("tau: 10.0", "tau: -1")
    text = text.replace("seed: 7", "seed: -3")
    wf.write_text(text)
    problems = _problems(wf, registry)
    joined = "\n".join(problems)
    assert "stages.5.with.tau: Input should be greater than 0" in joined
    assert ": seed: Input should be greater than or equal to 0" in joined
    assert "no stage provides 'composite' at epochs E0, E1" in joined
    assert len(problems) == 3


def test_yaml_syntax_error_has_position(tmp_path: Path, registry) -> None:
    wf = tmp_path / "broken.yaml"
    wf.write_text("name: x\nepochs: [\n  - id: E0\n")
    problems = _problems(wf, registry)
    assert len(problems) == 1 and "YAML syntax error" in problems[0]
    assert re.match(rf"^{re.escape(str(wf))}:\d+:\d+: ", problems[0])


def test_missing_input_file_unknown_epoch_and_duplicate_key(tmp_path: Path, registry) -> None:
    scene = make_cube_scene(tmp_path)
    wf = write_cube_workflow(scene)
    text = wf.read_text().replace("path: scan.ply", "path: nowhere.ply")
    text = text.replace("  - uses: fixed\n    role: as-is\n", "  - uses: fixed\n    epochs: [E2]\n    role: as-is\n")
    text = text.replace("seed: 7\n", "seed: 7\nseed: 8\n")
    wf.write_text(text)
    problems = _problems(wf, registry)
    joined = "\n".join(problems)
    assert "input file not found" in joined and "nowhere.ply" in joined
    assert "unknown epoch 'E2'" in joined
    assert "seed: key given twice" in joined


def test_reader_in_chain_and_unknown_reader(tmp_path: Path, registry) -> None:
    scene = make_cube_scene(tmp_path)
    wf = write_cube_workflow(scene)
    text = wf.read_text().replace("  - uses: identity\n", "  - uses: trimesh_mesh\n  - uses: identity\n")
    text = text.replace("{path: scan.ply, name: scan}", "{path: scan.ply, name: scan, reader: open3d_pts}")
    wf.write_text(text)
    joined = "\n".join(_problems(wf, registry))
    assert "'trimesh_mesh' is a reader" in joined
    assert "unknown reader 'open3d_pts'; did you mean 'open3d_points'" in joined


def test_valid_workflows_validate(tmp_path: Path, registry) -> None:
    scene = make_cube_scene(tmp_path)
    wf = load_workflow(write_cube_workflow(scene), registry)
    assert [e.id for e in wf.model.epochs] == ["E0", "E1"]
    assert wf.model.stages[5].with_.tau == 10.0
    res = run_gdt("validate", str(wf.path))
    assert res.returncode == 0 and "ok (2 epochs, 7 stages" in res.stdout


def test_schema_is_a_discriminated_union_on_uses(registry) -> None:
    schema = json_schema(registry)
    items = schema["properties"]["stages"]["items"]
    assert items["discriminator"]["propertyName"] == "uses"
    assert {"bhattacharyya", "fixed", "keep_unchanged", "constant"} <= set(items["discriminator"]["mapping"])
    fixed = schema["$defs"]["FixedParams"]
    assert fixed["additionalProperties"] is False and fixed["properties"]["tau"]["exclusiveMinimum"] == 0
    res = run_gdt("schema")
    assert res.returncode == 0 and '"discriminator"' in res.stdout


def test_shipped_workflows_reference_the_schema() -> None:
    for wf in (REPO / "workflows").glob("*.yaml"):
        assert "$schema=" in wf.read_text().splitlines()[0], wf


def test_committed_schema_matches_the_builtin_stages() -> None:
    """docs/gdt-workflow.schema.json is what editors validate against: it must follow the built-in stages."""
    from gdt_pipeline.plugins import load_registry

    builtin = load_registry(blocked={"gdt-c2c", "gdt-m3c2"})
    committed = json.loads((REPO / "docs" / "gdt-workflow.schema.json").read_text())
    assert committed == json.loads(json.dumps(json_schema(builtin))), (
        "regenerate with: GDT_BLOCKED_PLUGINS=c2c,m3c2 .venv/bin/gdt schema -o docs/gdt-workflow.schema.json")
