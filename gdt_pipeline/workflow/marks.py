"""YAML read with the safe loader, keeping every node's position so that problems point at ``file:line:col``.

The loader is bounded: a few hundred bytes of nested aliases (a "billion laughs" document) expand to billions of
nodes for anything that walks the data (the marks, pydantic), so nodes are counted as they are composed, each alias
counting as the whole subtree it stands for, and a document past ``MAX_NODES`` or ``MAX_DEPTH`` is refused.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from ..errors import WorkflowError

MAX_BYTES = 4 * 1024 * 1024  # a workflow is a few KB; larger is not a workflow
MAX_NODES = 100_000  # after alias expansion
MAX_DEPTH = 100


class Marks:
    """Positions of YAML nodes by path (tuple of keys and indices): value mark and, for mapping entries, key mark."""

    def __init__(self) -> None:
        self.value: dict[tuple, tuple[int, int]] = {}
        self.key: dict[tuple, tuple[int, int]] = {}
        self.duplicates: list[tuple[tuple, tuple[int, int]]] = []

    def walk(self, node: yaml.Node, path: tuple = ()) -> None:
        """Record the marks of ``node`` and everything under it (bounded by the loader's node limit)."""
        self.value[path] = (node.start_mark.line + 1, node.start_mark.column + 1)
        if isinstance(node, yaml.MappingNode):
            seen: set = set()
            for knode, vnode in node.value:
                # a complex key (a sequence or mapping) has no hashable value; it is named by its position
                key = knode.value if isinstance(knode, yaml.ScalarNode) else f"<key at {knode.start_mark.line + 1}>"
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


class LimitError(yaml.MarkedYAMLError):
    """A YAML document past the loader's limits (nodes after alias expansion, nesting depth)."""


class BoundedLoader(yaml.SafeLoader):
    """The safe loader, counting nodes as they are composed (aliases as the subtree they expand to) and depth."""

    def __init__(self, stream: str, max_nodes: int = MAX_NODES, max_depth: int = MAX_DEPTH) -> None:
        super().__init__(stream)
        self.max_nodes, self.max_depth = max_nodes, max_depth
        self.expanded: dict[int, int] = {}  # id(node) -> nodes it stands for, itself included
        self.depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        """Compose one node and refuse it when its expansion or the nesting depth passes the limits."""
        mark = self.peek_event().start_mark
        alias = self.check_event(yaml.AliasEvent)
        self.depth += 1
        if self.depth > self.max_depth:
            raise LimitError(problem=f"nested deeper than {self.max_depth} levels", problem_mark=mark)
        try:
            node = super().compose_node(parent, index)
        finally:
            self.depth -= 1
        if alias and id(node) not in self.expanded:
            # the anchored node is still being composed: the alias sits inside what it names, a cycle
            raise LimitError(problem="an alias inside the node it names (a recursive structure)", problem_mark=mark)
        if not alias:
            children: list = []
            if isinstance(node, yaml.SequenceNode):
                children = node.value
            elif isinstance(node, yaml.MappingNode):
                children = [n for pair in node.value for n in pair]
            self.expanded[id(node)] = 1 + sum(self.expanded.get(id(c), 1) for c in children)
        if self.expanded.get(id(node), 1) > self.max_nodes:
            raise LimitError(problem=f"too many nodes after alias expansion (more than {self.max_nodes})",
                                       problem_mark=mark)
        return node

    def construct_object(self, node: yaml.Node, deep: bool = False) -> Any:
        """Construct a value; a scalar Python rejects (a 13th month, a 5000-digit int) is an error at its node."""
        try:
            return super().construct_object(node, deep=deep)
        except (ValueError, TypeError, OverflowError) as exc:
            raise yaml.constructor.ConstructorError(None, None, f"cannot read this value: {exc}",
                                                    node.start_mark) from None


def loc_str(loc: tuple) -> str:
    """A location as dotted text (``stages.2.with.tau``)."""
    return ".".join(str(p) for p in loc) or "(top)"


def parse_bounded(text: str, where: str) -> tuple[yaml.Node | None, Any]:
    """The composed node tree and the constructed data of one YAML document, within the loader's limits.

    Raises ``ValueError`` with ``where:line:col: ...`` on a syntax error or a document past the limits.
    """
    loader = None
    try:
        loader = BoundedLoader(text)  # the reader already refuses control characters here
        node = loader.get_single_node()
        data = loader.construct_document(node) if node is not None else None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        at = f"{where}:{mark.line + 1}:{mark.column + 1}" if mark else where
        kind = "YAML document refused" if isinstance(exc, LimitError) else "YAML syntax error"
        raise ValueError(f"{at}: {kind}: {exc.problem or exc}") from None
    except yaml.YAMLError as exc:
        raise ValueError(f"{where}: YAML error: {exc}") from None
    except RecursionError:
        raise ValueError(f"{where}: YAML error: nested too deeply") from None
    finally:
        if loader is not None:
            loader.dispose()
    return node, data


def read_text_bounded(path: Path, what: str, max_bytes: int = MAX_BYTES) -> str:
    """A small text file's contents; ``ValueError`` naming the file when it is missing, a folder, too large or not
    UTF-8 text."""
    if not path.exists():
        raise ValueError(f"{path}: {what} not found")
    if path.is_dir():
        raise ValueError(f"{path}: is a directory, not a file")
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise ValueError(f"{path}: {what} is {size:,} bytes; more than {max_bytes:,} is not a {what}")
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read {what}: {exc}") from None


def read_yaml(path: Path) -> tuple[str, Any, Marks]:
    """A workflow file's text, data and node marks; :class:`WorkflowError` naming the place of any problem."""
    try:
        text = read_text_bounded(path, "workflow file")
        node, data = parse_bounded(text, str(path))
    except ValueError as exc:
        raise WorkflowError(str(path), [str(exc)]) from None
    marks = Marks()
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


