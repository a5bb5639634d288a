"""YAML read with the safe loader, keeping every node's position so that problems point at ``file:line:col``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from ..errors import WorkflowError


class Marks:
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


def loc_str(loc: tuple) -> str:
    return ".".join(str(p) for p in loc) or "(top)"


def read_yaml(path: Path) -> tuple[str, Any, Marks]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise WorkflowError(str(path), [f"{path}: workflow file not found"]) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise WorkflowError(str(path), [f"{path}: cannot read workflow file: {exc}"]) from None
    marks = Marks()
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


class Problems:
    def __init__(self, path: Path, marks: Marks) -> None:
        self.path, self.marks = path, marks
        self.items: list[tuple[tuple[int, int], str]] = []

    def add(self, loc: tuple, message: str, *, key: bool = False) -> None:
        line, col = self.marks.at(loc, key=key)
        self.items.append(((line, col), f"{self.path}:{line}:{col}: {loc_str(loc)}: {message}"))

    def sorted(self) -> list[str]:
        seen: set[str] = set()
        out = []
        for _, msg in sorted(self.items, key=lambda t: t[0]):
            if msg not in seen:
                seen.add(msg)
                out.append(msg)
        return out


