"""Property tests of the workflow loader: whatever the file holds, loading it either succeeds or raises WorkflowError.

Random YAML documents, random text, and mutations of the valid workflows (the shipped ones and the cube workflow of
the test scene): keys deleted, values of the wrong type, random scalars, shared nodes written as anchors and
aliases. Any other exception would reach the user as an internal error (exit 70).
"""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gdt_pipeline.errors import WorkflowError
from gdt_pipeline.workflow import load_workflow

from .conftest import REPO, make_cube_scene, write_cube_workflow

# bounded so that the file runs in under 30 s; GDT_HYPOTHESIS_EXAMPLES=1000 searches harder
SETTINGS = settings(max_examples=int(os.environ.get("GDT_HYPOTHESIS_EXAMPLES", "60")), deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])

scalars = st.one_of(st.none(), st.booleans(), st.integers(min_value=-(2**70), max_value=2**70),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
                    st.sampled_from(["E0", "E1", "as-is", "as-designed", "constant", "nearest", "keep_unchanged",
                                     "most_reliable", "sensor_model", "given", "cad.obj", "scan.ply", "..", "/",
                                     "tof_low_cost", "mm", "m", "2001-13-45", ".inf", "-1"]))
values = st.recursive(scalars, lambda kids: st.one_of(st.lists(kids, max_size=4),
                                                       st.dictionaries(st.one_of(st.text(max_size=8), st.integers()),
                                                                       kids, max_size=4)), max_leaves=20)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The cube scene with its valid workflow, shared by all examples (the loader only reads it)."""
    scene = make_cube_scene(tmp_path_factory.mktemp("props") / "scene")
    write_cube_workflow(scene)
    return scene.dir


def _bases(scene_dir: Path) -> list[tuple[str, Any]]:
    """(name, data) of every valid workflow: the cube workflow and the shipped ones."""
    out = [("cube", yaml.safe_load((scene_dir / "workflow.yaml").read_text()))]
    out += [(p.name, yaml.safe_load(p.read_text())) for p in sorted((REPO / "workflows").glob("*.yaml"))]
    return out


def _load(scene_dir: Path, text: str, registry: Any, name: str = "prop.yaml") -> None:
    """Load ``text`` as a workflow beside the scene: it loads, or raises WorkflowError with located problems."""
    path = scene_dir / name
    path.write_text(text, encoding="utf-8")
    try:
        load_workflow(path, registry)
    except WorkflowError as exc:
        assert exc.problems and all(isinstance(p, str) and p.startswith(str(path)) for p in exc.problems), exc


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path (keys and indices) into nested dicts and lists."""
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


def _parent(data: Any, path: tuple) -> Any:
    for p in path[:-1]:
        data = data[p]
    return data


def _mutate(data: Any, path: tuple, how: str, value: Any, other: tuple) -> Any:
    """One mutation at ``path``: delete it, set a value (random scalar or structure), or share another node there
    (dumped as an anchor and an alias)."""
    data = copy.deepcopy(data)
    if not path:
        return value if how != "delete" else None
    parent = _parent(data, path)
    if how == "delete":
        del parent[path[-1]]
    elif how == "alias":
        target = data
        for p in other:
            target = target[p]
        if target is not parent:  # a node aliased inside itself would be a cycle, which YAML cannot dump safely
            parent[path[-1]] = target
    else:
        parent[path[-1]] = value
    return data


@SETTINGS
@given(doc=values)
def test_random_documents_load_or_raise_workflow_error(scene_dir: Path, registry: Any, doc: Any) -> None:
    _load(scene_dir, yaml.safe_dump(doc, allow_unicode=True), registry)


@SETTINGS
@given(text=st.text(alphabet=st.sampled_from([*"abc:-[]{}&*!|>'\"#%@`, \n\t0.1eE+", "\u00e9", "\x00"]),
                    max_size=200))
def test_random_text_loads_or_raises_workflow_error(scene_dir: Path, registry: Any, text: str) -> None:
    _load(scene_dir, text, registry)


@SETTINGS
@given(data=st.data(), how=st.sampled_from(["delete", "scalar", "structure", "alias"]))
def test_mutated_valid_workflows_load_or_raise_workflow_error(scene_dir: Path, registry: Any, data: st.DataObject,
                                                               how: str) -> None:
    _, base = data.draw(st.sampled_from(_bases(scene_dir)), label="workflow")
    paths = _paths(base)
    path = data.draw(st.sampled_from(paths), label="path")
    other = data.draw(st.sampled_from(paths), label="aliased")
    value = data.draw(scalars if how == "scalar" else values, label="value")
    mutated = _mutate(base, path, how, value, other)
    _load(scene_dir, yaml.safe_dump(mutated, allow_unicode=True), registry)


@SETTINGS
@given(depth=st.integers(1, 400), width=st.integers(1, 12))
def test_nested_and_aliased_documents_are_bounded(scene_dir: Path, registry: Any, depth: int, width: int) -> None:
    """Deep nesting and alias fan-out beyond the limits are refused with a position, below them they load."""
    nested = "x: " + "[" * depth + "1" + "]" * depth + "\n"
    _load(scene_dir, nested, registry)
    lines = ["a0: &a0 [1, 2, 3]"] + [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * width)}]" for i in range(1, 8)]
    _load(scene_dir, "\n".join(lines) + "\n", registry)
