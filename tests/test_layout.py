"""The layout rules of docs/engine.md, checked on the source tree: the engine and the stages never import the
simulation or evaluation code, no module imports another module's private names, files stay readable in one
sitting and functions do one job."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCE_DIRS = ("gdt_pipeline", "stages", "twin_store", "plugins", "tests", "bench")
MAX_FILE_LINES = 400
MAX_FUNCTION_LINES = 60
ONE_PIECE = "one piece"  # a longer function's docstring must say why it must be one piece
LAB_PACKAGES = ("gdt_pipeline.simulation", "gdt_pipeline.evaluation")
# The CLI's simulation and evaluation commands are the front door to those packages, so they may import them.
LAB_FRONT = {"gdt_pipeline/cli/lab_commands.py"}


def _sources() -> list[Path]:
    out = []
    for top in SOURCE_DIRS:
        out += [p for p in (ROOT / top).rglob("*.py") if ".venv" not in p.parts and "build" not in p.parts]
    return sorted(out)


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[0] == "plugins":  # plugins/<dist>/<package>/...
        parts = parts[2:]
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _absolute(node: ast.ImportFrom, path: Path) -> str:
    """The absolute module an ``ImportFrom`` names (relative imports resolved against the file's package)."""
    if not node.level:
        return node.module or ""
    package = _module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(path: Path) -> list[tuple[str, list[str], int]]:
    """(module, imported names, line) of every import in a file, at any depth."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            out.append((_absolute(node, path), [a.name for a in node.names], node.lineno))
    return out


def _is_lab(module: str) -> bool:
    return any(module == p or module.startswith(p + ".") for p in LAB_PACKAGES)


def test_engine_and_stages_never_import_simulation_or_evaluation() -> None:
    bad = []
    for path in _sources():
        rel = path.relative_to(ROOT).as_posix()
        mod = _module_name(path)
        if not (rel.startswith(("gdt_pipeline/", "stages/", "plugins/"))) or _is_lab(mod) or rel in LAB_FRONT:
            continue
        for module, names, line in _imports(path):
            targets = [module] + [f"{module}.{n}" for n in names]
            if any(_is_lab(t) for t in targets):
                bad.append(f"{rel}:{line} imports {module}")
    assert not bad, "\n".join(bad)


def test_no_module_imports_a_private_name_of_another() -> None:
    bad = []
    for path in _sources():
        rel = path.relative_to(ROOT).as_posix()
        for module, names, line in _imports(path):
            private = [n for n in names if n.startswith("_") and not n.startswith("__")]
            if private:
                bad.append(f"{rel}:{line} imports {', '.join(private)} from {module}")
    assert not bad, "\n".join(bad)


def test_layout_checks_see_the_tree() -> None:
    """The checks above must be looking at real files (a wrong ROOT would pass them vacuously)."""
    files = {p.relative_to(ROOT).as_posix() for p in _sources()}
    assert "gdt_pipeline/runner.py" in files or "gdt_pipeline/runner/__init__.py" in files
    assert any(f.startswith("stages/distance/") for f in files)
    assert _absolute(ast.parse("from ..types import Dataset").body[0], ROOT / "gdt_pipeline/geometry/x.py") \
        == "gdt_pipeline.types"


@pytest.mark.parametrize("path", _sources(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_file_is_short_enough_to_read_in_one_sitting(path: Path) -> None:
    n = len(path.read_text(encoding="utf-8").splitlines())
    assert n <= MAX_FILE_LINES, f"{path.relative_to(ROOT)} has {n} lines (at most {MAX_FILE_LINES})"


def test_functions_do_one_job() -> None:
    bad = []
    for path in _sources():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            length = node.end_lineno - node.lineno + 1
            doc = ast.get_docstring(node) or ""
            if length > MAX_FUNCTION_LINES and ONE_PIECE not in doc:
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} has {length} lines")
    assert not bad, "\n".join(bad)


def test_the_records_and_the_plugin_api_pass_mypy_strict() -> None:
    """``mypy --strict`` on what `[tool.mypy] files` names (the types and the API plugins build on), as `make lint`."""
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-m", "mypy"], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
