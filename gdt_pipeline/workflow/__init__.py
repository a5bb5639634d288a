"""Workflow files: YAML (safe loader only) validated by pydantic, every problem reported at once with its position.

The model is built from the registry: each chain stage contributes a model ``{uses: Literal[name], with: Params}``
and they join a discriminated union on ``uses``. Pydantic's error locations are mapped back to the YAML nodes'
marks, so a problem reads ``file:line:col: stages.2.with.tau: message``.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from ..errors import WorkflowError
from ..plugins import Registry
from .checks import param_problems, pydantic_problems, reference_problems, slot_problems
from .marks import Problems, loc_str, read_yaml
from .model import (
    EpochSpec,
    InputSpec,
    LoadedWorkflow,
    StageEntryBase,
    WorkflowBase,
    json_schema,
    workflow_model,
)
from .stations import station_problems


def load_workflow(path: str | Path, registry: Registry, *, check_files: bool = True,
                  held: frozenset[str] = frozenset()) -> LoadedWorkflow:
    """Read and validate a workflow file; raise :class:`WorkflowError` listing every problem found. The input files
    of the epochs in ``held`` (a twin holds them) need not exist."""
    path = Path(path).resolve()
    text, data, marks = read_yaml(path)
    problems = Problems(path, marks)
    if not isinstance(data, dict):
        problems.add((), "a workflow file must be a YAML mapping (name, twin, epochs, stages)")
        raise WorkflowError(str(path), problems.sorted())
    for loc, (line, col) in marks.duplicates:
        problems.items.append(((line, col), f"{path}:{line}:{col}: {loc_str(loc)}: key given twice"))
    model_cls = workflow_model(registry)
    model = None
    try:
        model = model_cls.model_validate(data)
    except ValidationError as exc:
        pydantic_problems(exc, data, registry, problems)
    slot_problems(data, registry, problems)
    if check_files:
        reference_problems(data, registry, problems, path.parent, held)
        if model is not None:
            param_problems(model, registry, problems, path.parent)
            station_problems(model, registry, problems, path.parent, held)
    if problems.items:
        raise WorkflowError(str(path), problems.sorted())
    return LoadedWorkflow(path=path, sha256=hashlib.sha256(text.encode()).hexdigest(), model=model, text=text)


def iter_chain(wf: LoadedWorkflow, epoch: EpochSpec) -> Iterator[tuple[int, Any]]:
    """The chain entries (with their index in the file) that run in ``epoch``."""
    for index, entry in enumerate(wf.model.stages):
        if entry.applies_to(epoch):
            yield index, entry


__all__ = ["EpochSpec", "InputSpec", "LoadedWorkflow", "StageEntryBase", "WorkflowBase", "iter_chain", "json_schema",
           "load_workflow", "workflow_model"]
