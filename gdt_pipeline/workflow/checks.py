"""Workflow checks: pydantic's errors mapped to YAML positions, the slot chain per epoch, epoch and file references."""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from ..plugins import Registry, unknown_name_message
from ..slots import ENGINE_SLOTS, FINAL_SLOT
from .marks import Problems
from .model import EpochSpec, InputSpec, StageEntryBase, WorkflowBase


def allowed_keys(loc: tuple, data: Any, registry: Registry) -> list[str] | None:
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


def strip_tags(loc: tuple, data: Any) -> tuple:
    """Drop the discriminator tag pydantic inserts after a stage index (stages.2.fixed.with -> stages.2.with)."""
    if len(loc) >= 3 and loc[0] == "stages" and isinstance(loc[1], int) and isinstance(loc[2], str):
        try:
            if data["stages"][loc[1]]["uses"] == loc[2]:
                return loc[:2] + loc[3:]
        except (KeyError, IndexError, TypeError):
            pass
    return loc


def pydantic_problems(exc: ValidationError, data: Any, registry: Registry, problems: Problems) -> None:
    for err in exc.errors(include_url=False):
        # a default `with` is validated under the field's own name
        loc = strip_tags(tuple("with" if p == "with_" else p for p in err["loc"]), data)
        etype = err["type"]
        if etype == "union_tag_invalid":
            tag = err.get("ctx", {}).get("tag", "?")
            problems.add((*loc, "uses"), unknown_name_message("stage", tag, registry.names(chain_only=True)))
        elif etype == "union_tag_not_found":
            problems.add(loc, "each stage needs `uses: <stage name>`")
        elif etype == "extra_forbidden":
            allowed = allowed_keys(loc, data, registry) or []
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


def listed(value: Any) -> list:
    """``value`` when it is a list, else empty: the checks below also run on data the schema rejected."""
    return value if isinstance(value, list) else []


def slot_problems(data: dict, registry: Registry, problems: Problems) -> None:
    """Check per epoch that every slot a stage requires is provided by the engine or an earlier stage."""
    epochs = [e for e in listed(data.get("epochs")) if isinstance(e, dict)]
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


def reference_problems(data: dict, registry: Registry, problems: Problems, base: Path,
                       held: frozenset[str] = frozenset()) -> None:
    """Checks that need more than the schema: epoch references, reader and executor names, input files present
    (except those of the epochs in ``held``, which a twin holds: their files may be gone)."""
    epochs = [e for e in listed(data.get("epochs")) if isinstance(e, dict)]
    ids = [e.get("id") for e in epochs]
    for s_index, entry in enumerate(listed(data.get("stages"))):
        if not isinstance(entry, dict):
            continue
        name = entry.get("uses")
        if isinstance(name, str) and name in registry.names("reader"):
            problems.add(("stages", s_index, "uses"),
                         f"{name!r} is a reader: readers are chosen per input (set `reader:` on the input), "
                         f"not chained under stages")
        for j, eid in enumerate(listed(entry.get("epochs"))):
            if eid not in ids:
                problems.add(("stages", s_index, "epochs", j),
                             unknown_name_message("epoch", str(eid), [str(i) for i in ids]))
    execution = data.get("execution")
    executor = execution.get("executor") if isinstance(execution, dict) else None
    if isinstance(executor, str) and executor not in {e.name for e in registry.executors()}:
        problems.add(("execution", "executor"),
                     unknown_name_message("executor", executor, [e.name for e in registry.executors()]))
    for e_index, epoch in enumerate(epochs):
        inputs = [(i, inp) for i, inp in enumerate(listed(epoch.get("inputs"))) if isinstance(inp, dict)]
        for i_index, inp in inputs:
            if str(epoch.get("id")) in held and not _exists(base, inp.get("path")):
                continue
            input_problems(inp, ("epochs", e_index, "inputs", i_index), registry, problems, base)
        names = [str(inp.get("name") or Path(str(inp.get("path", ""))).stem) for _, inp in inputs]
        dups = sorted({n for n in names if names.count(n) > 1})
        if dups:
            problems.add(("epochs", e_index, "inputs"),
                         f"dataset names must be unique within an epoch; repeated: {', '.join(dups)} "
                         f"(set `name:` on the inputs)")


def _exists(base: Path, path: Any) -> bool:
    """Whether an input's path names something that exists (False for what is not a usable path)."""
    try:
        return isinstance(path, str) and (base / path).exists()
    except (OSError, ValueError):
        return False


def input_problems(inp: dict, loc: tuple, registry: Registry, problems: Problems, base: Path) -> None:
    """One input: its reader is installed, its path is a file (not a folder) that an installed reader accepts."""
    reader = inp.get("reader")
    if isinstance(reader, str) and reader not in registry.names("reader"):
        problems.add((*loc, "reader"), unknown_name_message("reader", reader, registry.names("reader")))
    path = inp.get("path")
    if not isinstance(path, str):
        return
    try:
        full = (base / path).resolve()
        is_dir, is_file = full.is_dir(), full.is_file()
    except (OSError, ValueError) as exc:  # a name too long, a NUL byte
        problems.add((*loc, "path"), f"not a usable file path: {exc}")
        return
    if is_dir:
        problems.add((*loc, "path"), f"{full} is a directory, not a file")
    elif not is_file:
        problems.add((*loc, "path"), f"input file not found: {full}")
    elif reader is None:
        kind = inp.get("kind") if inp.get("kind") in ("mesh", "points") else None
        try:
            accepted = registry.readers_for(full, kind)
        except Exception as exc:  # a reader's `accepts` is plugin code; its failure names the file, not a crash
            problems.add((*loc, "path"), f"cannot tell which reader accepts {full.name!r}: {type(exc).__name__}: "
                                         f"{exc}")
            return
        if not accepted:
            exts = sorted({x for s in registry.stages("reader") for x in s.extensions})
            problems.add((*loc, "path"), f"no installed reader accepts {full.name!r} (extensions: {', '.join(exts)})")
            return
        reader = accepted[0].name
    if isinstance(reader, str) and reader in registry.names("reader") and isinstance(inp.get("with"), dict):
        reader_param_problems(registry.reader(reader), inp["with"], (*loc, "with"), problems)


def reader_param_problems(spec: Any, params: dict, loc: tuple, problems: Problems) -> None:
    """An input's ``with:`` checked against the params model of the reader that will read it."""
    try:
        spec.params.model_validate(params)
    except ValidationError as exc:
        for err in exc.errors(include_url=False):
            problems.add((*loc, *err["loc"]), f"reader {spec.name!r}: {err['msg']}")


def param_problems(model: Any, registry: Registry, problems: Problems, base: Path) -> None:
    """Each chain entry's ``validate`` hook: what its params name outside the workflow (files), before any run."""
    for s_index, entry in enumerate(model.stages):
        spec = registry.get(entry.uses)
        if spec.validate is None:
            continue
        try:
            found = list(spec.validate(entry.with_, base))
        except Exception as exc:  # plugin code: its failure is a problem of this entry, not a crash of validate
            problems.add(("stages", s_index, "with"), f"stage {spec.name!r} ({spec.plugin}) failed to check its "
                                                      f"parameters: {type(exc).__name__}: {exc}")
            continue
        for key, message in found:
            sub = tuple(int(p) if p.isdigit() else p for p in str(key).split(".") if p)
            problems.add(("stages", s_index, "with", *sub), message)
