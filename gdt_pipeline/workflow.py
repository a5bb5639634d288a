"""Workflow files: YAML (safe loader only) validated by pydantic, every problem reported at once with its position.

The model is built from the registry: each chain stage contributes a model ``{uses: Literal[name], with: Params}``
and they join a discriminated union on ``uses``. Pydantic's error locations are mapped back to the YAML nodes'
marks, so a problem reads ``file:line:col: stages.2.with.tau: message``.
"""

from __future__ import annotations

import difflib
import hashlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model, field_validator

from .errors import WorkflowError
from .plugins import Registry, StageSpec, unknown_name_message

Units = Literal["m", "dm", "cm", "mm", "um", "in", "ft"]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Identifier = Annotated[str, Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$", max_length=64)]

# Slots the engine itself puts into every epoch's context before the chain runs; "reference" only once a composite
# exists, i.e. from the second epoch on.
ENGINE_SLOTS = frozenset({"recent", "epoch"})
FINAL_SLOT = "composite"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class InputSpec(_Strict):
    """One input file of an epoch."""

    path: str = Field(description="File path, relative to the workflow file.")
    name: Identifier | None = Field(None, description="Dataset name in the twin; default: the file stem.")
    kind: Literal["mesh", "points"] | None = Field(None, description="Force mesh or point reading (PLY can be both).")
    units: Units | None = Field(None, description="Units the file is written in; default: the workflow's units.")
    reader: str | None = Field(None, description="Reader stage to use; default: chosen by file extension.")
    viewpoints: list[Vec3] | None = Field(None, description="Sensor positions (in the file's units), if known.")


class EpochSpec(_Strict):
    """One epoch: its id, role and input files."""

    id: Identifier
    role: Literal["as-designed", "as-is"]
    inputs: list[InputSpec] = Field(min_length=1)
    description: str = ""


class StageEntryBase(_Strict):
    """Fields every chain entry has besides ``uses`` and ``with``."""

    id: Identifier | None = Field(None, description="Optional label for logs and provenance.")
    role: Literal["as-designed", "as-is"] | None = Field(None, description="Run only in epochs of this role.")
    epochs: list[str] | None = Field(None, description="Run only in these epochs (ids).")

    def applies_to(self, epoch: EpochSpec) -> bool:
        """Whether this chain entry runs in ``epoch``."""
        return (self.role is None or self.role == epoch.role) and (self.epochs is None or epoch.id in self.epochs)


class WorkflowBase(_Strict):
    """Fields of a workflow file other than the chain."""

    name: str = Field(min_length=1)
    description: str = ""
    twin: str = Field(description="Twin folder to write, relative to the workflow file.")
    seed: int = Field(0, ge=0, lt=2**63, description="Seed of every random draw of the run.")
    units: Units = Field("m", description="Units of the twin.")
    up_axis: Literal["Y", "Z"] = "Z"
    epochs: list[EpochSpec] = Field(min_length=1)

    @field_validator("epochs")
    @classmethod
    def _unique_epoch_ids(cls, epochs: list[EpochSpec]) -> list[EpochSpec]:
        ids = [e.id for e in epochs]
        dups = sorted({i for i in ids if ids.count(i) > 1})
        if dups:
            raise ValueError(f"epoch ids must be unique; repeated: {', '.join(dups)}")
        return epochs


@dataclass(frozen=True)
class LoadedWorkflow:
    """A validated workflow with where it came from."""

    path: Path
    sha256: str
    model: Any  # an instance of the registry-built Workflow model
    text: str

    @property
    def dir(self) -> Path:
        """Folder the workflow's relative paths are resolved against."""
        return self.path.parent

    def twin_path(self) -> Path:
        """The twin folder the workflow names, resolved."""
        return (self.dir / self.model.twin).resolve()

    def input_path(self, inp: InputSpec) -> Path:
        """An input's file path, resolved."""
        return (self.dir / inp.path).resolve()


def _entry_model(spec: StageSpec) -> type[BaseModel]:
    return create_model(
        f"Stage_{spec.name}",
        __base__=StageEntryBase,
        __doc__=f"{spec.family} stage {spec.name!r} ({spec.plugin} {spec.plugin_version}). {spec.description}".strip(),
        uses=(Literal[spec.name], Field(description=spec.description or spec.name)),  # type: ignore[valid-type]
        with_=(spec.params, Field(default_factory=spec.params, alias="with")),
    )


def workflow_model(registry: Registry) -> type[BaseModel]:
    """The pydantic model of a workflow file for the stages installed now (a discriminated union on ``uses``)."""
    entries = [_entry_model(registry.get(n)) for n in registry.names(chain_only=True)]
    if not entries:
        entry_type: Any = StageEntryBase
    elif len(entries) == 1:
        entry_type = entries[0]
    else:
        entry_type = Annotated[Union[tuple(entries)], Field(discriminator="uses")]  # noqa: UP007
    return create_model("Workflow", __base__=WorkflowBase, stages=(list[entry_type], Field(min_length=1)))


def json_schema(registry: Registry) -> dict[str, Any]:
    """JSON Schema of workflow files, for editors (``# yaml-language-server: $schema=...``)."""
    schema = workflow_model(registry).model_json_schema(by_alias=True)
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "gdt-pipeline workflow"
    return schema


# ---------------------------------------------------------------------------------------------------------------------
# YAML with positions


class _Marks:
    """Positions of YAML nodes by path (tuple of keys and indices): value mark and, for mapping entries, key mark."""

    def __init__(self) -> None:
        self.value: dict[tuple, tuple[int, int]] = {}
        self.key: dict[tuple, tuple[int, int]] = {}
        self.duplicates: list[tuple[tuple, tuple[int, int]]] = []

    def walk(self, node: yaml.Node, path: tuple = ()) -> None:
        self.value[path] = (node.start_mark.line + 1, node.start_mark.column + 1)
        if isinstance(node, yaml.MappingNode):
            seen: set = set()
            for knode, vnode in node.value:
                key = knode.value
                if key in seen:
                    self.duplicates.append(((*path, key), (knode.start_mark.line + 1, knode.start_mark.column + 1)))
                seen.add(key)
                self.key[(*path, key)] = (knode.start_mark.line + 1, knode.start_mark.column + 1)
                self.walk(vnode, (*path, key))
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                self.walk(item, (*path, i))

    def at(self, loc: tuple, *, key: bool = False) -> tuple[int, int]:
        """Line and column for a location: the key's mark when asked and known, else the nearest enclosing value."""
        if key and loc in self.key:
            return self.key[loc]
        probe = loc
        while probe not in self.value and probe:
            probe = probe[:-1]
        return self.value.get(probe, (1, 1))


def _loc_str(loc: tuple) -> str:
    return ".".join(str(p) for p in loc) or "(top)"


def _read_yaml(path: Path) -> tuple[str, Any, _Marks]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise WorkflowError(str(path), [f"{path}: workflow file not found"]) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise WorkflowError(str(path), [f"{path}: cannot read workflow file: {exc}"]) from None
    marks = _Marks()
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark else str(path)
        raise WorkflowError(str(path), [f"{where}: YAML syntax error: {exc.problem or exc}"]) from None
    except yaml.YAMLError as exc:
        raise WorkflowError(str(path), [f"{path}: YAML error: {exc}"]) from None
    if node is not None:
        marks.walk(node)
    return text, data, marks


# ---------------------------------------------------------------------------------------------------------------------
# Validation


class _Problems:
    def __init__(self, path: Path, marks: _Marks) -> None:
        self.path, self.marks = path, marks
        self.items: list[tuple[tuple[int, int], str]] = []

    def add(self, loc: tuple, message: str, *, key: bool = False) -> None:
        line, col = self.marks.at(loc, key=key)
        self.items.append(((line, col), f"{self.path}:{line}:{col}: {_loc_str(loc)}: {message}"))

    def sorted(self) -> list[str]:
        seen: set[str] = set()
        out = []
        for _, msg in sorted(self.items, key=lambda t: t[0]):
            if msg not in seen:
                seen.add(msg)
                out.append(msg)
        return out


def _allowed_keys(loc: tuple, data: Any, registry: Registry) -> list[str] | None:
    """Field names allowed at the mapping that holds the last element of ``loc``, for "did you mean"."""
    parent = loc[:-1]

    def fields(model: type[BaseModel]) -> list[str]:
        return [f.alias or n for n, f in model.model_fields.items()]

    if parent == ():
        return [*fields(WorkflowBase), "stages"]
    if len(parent) == 2 and parent[0] == "epochs":
        return fields(EpochSpec)
    if len(parent) == 4 and parent[0] == "epochs" and parent[2] == "inputs":
        return fields(InputSpec)
    if len(parent) == 2 and parent[0] == "stages":
        return [*fields(StageEntryBase), "uses", "with"]
    if len(parent) == 3 and parent[0] == "stages" and parent[2] == "with":
        try:
            uses = data["stages"][parent[1]]["uses"]
            return fields(registry.get(uses).params)
        except Exception:
            return None
    return None


def _strip_tags(loc: tuple, data: Any) -> tuple:
    """Drop the discriminator tag pydantic inserts after a stage index (stages.2.fixed.with -> stages.2.with)."""
    if len(loc) >= 3 and loc[0] == "stages" and isinstance(loc[1], int) and isinstance(loc[2], str):
        try:
            if data["stages"][loc[1]]["uses"] == loc[2]:
                return loc[:2] + loc[3:]
        except (KeyError, IndexError, TypeError):
            pass
    return loc


def _pydantic_problems(exc: ValidationError, data: Any, registry: Registry, problems: _Problems) -> None:
    for err in exc.errors(include_url=False):
        loc = _strip_tags(tuple(err["loc"]), data)
        etype = err["type"]
        if etype == "union_tag_invalid":
            tag = err.get("ctx", {}).get("tag", "?")
            problems.add((*loc, "uses"), unknown_name_message("stage", tag, registry.names(chain_only=True)))
        elif etype == "union_tag_not_found":
            problems.add(loc, "each stage needs `uses: <stage name>`")
        elif etype == "extra_forbidden":
            allowed = _allowed_keys(loc, data, registry) or []
            name = str(loc[-1])
            hit = difflib.get_close_matches(name, allowed, n=1, cutoff=0.6)
            if loc[0] == "stages" and loc[2:3] == ("with",):
                what = f"unknown parameter {name!r} of stage {data['stages'][loc[1]]['uses']!r}"
            else:
                what = f"unknown key {name!r}"
            mean = f"; did you mean {hit[0]!r}?" if hit else ""
            problems.add(loc, f"{what}{mean} (allowed: {', '.join(allowed) or 'none'})", key=True)
        elif etype == "missing":
            problems.add(loc, f"missing required key {loc[-1]!r}", key=False)
        else:
            problems.add(loc, err["msg"])


def _slot_problems(data: dict, registry: Registry, problems: _Problems) -> None:
    """Check per epoch that every slot a stage requires is provided by the engine or an earlier stage."""
    epochs = [e for e in data.get("epochs") or [] if isinstance(e, dict)]
    stages = data.get("stages") or []
    if not isinstance(stages, list) or not epochs:
        return
    epoch_ids = [e.get("id") for e in epochs]
    missing: dict[tuple[int, str], list[str]] = {}
    checks: dict[tuple[int, str], list[str]] = {}
    no_final: list[str] = []
    for e_index, epoch in enumerate(epochs):
        available = set(ENGINE_SLOTS) | ({"reference"} if e_index > 0 else set())
        for s_index, entry in enumerate(stages):
            if not isinstance(entry, dict) or not isinstance(entry.get("uses"), str):
                continue
            name = entry["uses"]
            spec = registry.get(name) if name in registry.names(chain_only=True) else registry.closest(name)
            if spec is None:
                continue
            role, only = entry.get("role"), entry.get("epochs")
            if role is not None and role != epoch.get("role"):
                continue
            if isinstance(only, list) and epoch.get("id") not in only:
                continue
            for slot in spec.requires:
                if slot not in available:
                    missing.setdefault((s_index, slot), []).append(str(epoch.get("id")))
            if spec.check is not None:
                msg = spec.check(frozenset(available))
                if msg:
                    checks.setdefault((s_index, msg), []).append(str(epoch.get("id")))
            available |= set(spec.provides)
        if FINAL_SLOT not in available:
            no_final.append(str(epoch.get("id")))
    for (s_index, slot), at in missing.items():
        name = repr(stages[s_index]["uses"])
        if stages[s_index]["uses"] not in registry:
            spec = registry.closest(stages[s_index]["uses"])
            name = f"{name} (read as {spec.name!r})" if spec else name
        hint = ""
        if slot == "reference" and epoch_ids and at[0] == epoch_ids[0]:
            hint = " (the first epoch has no reference yet: limit the stage with `role: as-is` or `epochs: [...]`)"
        producers = [s.name for s in registry.stages() if slot in s.provides]
        prod = f"; stages that provide it: {', '.join(producers)}" if producers else ""
        problems.add(("stages", s_index, "uses"),
                     f"stage {name} requires slot {slot!r}, which no earlier stage provides "
                     f"at epoch{'s' if len(at) > 1 else ''} {', '.join(at)}{hint}{prod}")
    for (s_index, msg), at in checks.items():
        problems.add(("stages", s_index, "uses"), f"{msg} (at epoch{'s' if len(at) > 1 else ''} {', '.join(at)})")
    if no_final:
        problems.add(("stages",), f"no stage provides {FINAL_SLOT!r} at epoch{'s' if len(no_final) > 1 else ''} "
                                  f"{', '.join(no_final)}: end the chain with a fusion stage")


def _reference_problems(data: dict, registry: Registry, problems: _Problems, base: Path) -> None:
    """Checks that need more than the schema: epoch references, reader names, input files present."""
    epochs = [e for e in data.get("epochs") or [] if isinstance(e, dict)]
    ids = [e.get("id") for e in epochs]
    for s_index, entry in enumerate(data.get("stages") or []):
        if not isinstance(entry, dict):
            continue
        name = entry.get("uses")
        if isinstance(name, str) and name in registry.names("reader"):
            problems.add(("stages", s_index, "uses"),
                         f"{name!r} is a reader: readers are chosen per input (set `reader:` on the input), "
                         f"not chained under stages")
        for j, eid in enumerate(entry.get("epochs") or []):
            if eid not in ids:
                problems.add(("stages", s_index, "epochs", j), unknown_name_message("epoch", str(eid), ids))
    for e_index, epoch in enumerate(epochs):
        for i_index, inp in enumerate(epoch.get("inputs") or []):
            if not isinstance(inp, dict):
                continue
            reader = inp.get("reader")
            if isinstance(reader, str) and reader not in registry.names("reader"):
                problems.add(("epochs", e_index, "inputs", i_index, "reader"),
                             unknown_name_message("reader", reader, registry.names("reader")))
            path = inp.get("path")
            if isinstance(path, str):
                full = (base / path).resolve()
                if not full.is_file():
                    problems.add(("epochs", e_index, "inputs", i_index, "path"), f"input file not found: {full}")
                elif reader is None and not registry.readers_for(full, inp.get("kind")):
                    exts = sorted({x for s in registry.stages("reader") for x in s.extensions})
                    problems.add(("epochs", e_index, "inputs", i_index, "path"),
                                 f"no installed reader accepts {full.name!r} (extensions: {', '.join(exts)})")
        names = [inp.get("name") or Path(str(inp.get("path", ""))).stem
                 for inp in epoch.get("inputs") or [] if isinstance(inp, dict)]
        dups = sorted({n for n in names if names.count(n) > 1})
        if dups:
            problems.add(("epochs", e_index, "inputs"),
                         f"dataset names must be unique within an epoch; repeated: {', '.join(dups)} "
                         f"(set `name:` on the inputs)")


def load_workflow(path: str | Path, registry: Registry, *, check_files: bool = True) -> LoadedWorkflow:
    """Read and validate a workflow file; raise :class:`WorkflowError` listing every problem found."""
    path = Path(path).resolve()
    text, data, marks = _read_yaml(path)
    problems = _Problems(path, marks)
    if not isinstance(data, dict):
        problems.add((), "a workflow file must be a YAML mapping (name, twin, epochs, stages)")
        raise WorkflowError(str(path), problems.sorted())
    for loc, (line, col) in marks.duplicates:
        problems.items.append(((line, col), f"{path}:{line}:{col}: {_loc_str(loc)}: key given twice"))
    model_cls = workflow_model(registry)
    model = None
    try:
        model = model_cls.model_validate(data)
    except ValidationError as exc:
        _pydantic_problems(exc, data, registry, problems)
    _slot_problems(data, registry, problems)
    if check_files:
        _reference_problems(data, registry, problems, path.parent)
    if problems.items:
        raise WorkflowError(str(path), problems.sorted())
    return LoadedWorkflow(path=path, sha256=hashlib.sha256(text.encode()).hexdigest(), model=model, text=text)


def iter_chain(wf: LoadedWorkflow, epoch: EpochSpec) -> Iterator[tuple[int, Any]]:
    """The chain entries (with their index in the file) that run in ``epoch``."""
    for index, entry in enumerate(wf.model.stages):
        if entry.applies_to(epoch):
            yield index, entry

