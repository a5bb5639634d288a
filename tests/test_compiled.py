"""The compiled kernels' disk cache: a kernel calling a kernel of a sibling module sees that module's change (numba's
own cache would keep the old machine code), and the cache lands under ``$GDT_CACHE_DIR``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

CALLEE = """from gdt_pipeline.compiled import njit


@njit
def step(x):
    return x + {step}
"""
CALLER = """from gdt_pipeline.compiled import njit

from .callee import step


@njit
def twice(x):
    return step(step(x))
"""


def _run(root: Path, cache: Path) -> int:
    env = {**os.environ, "GDT_CACHE_DIR": str(cache), "PYTHONPATH": str(root)}
    out = subprocess.run([sys.executable, "-c", "from kernels.caller import twice; print(twice(1))"], env=env,
                         capture_output=True, text=True, check=True)
    return int(out.stdout.strip())


def test_a_changed_sibling_module_is_recompiled(tmp_path: Path) -> None:
    pkg = tmp_path / "kernels"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "callee.py").write_text(CALLEE.format(step=1))
    (pkg / "caller.py").write_text(CALLER)
    cache = tmp_path / "cache"
    assert _run(tmp_path, cache) == 3
    assert any(cache.rglob("caller.twice-*.nbi"))  # cached where asked
    assert _run(tmp_path, cache) == 3  # from the cache
    (pkg / "callee.py").write_text(CALLEE.format(step=10))  # the caller's own file is unchanged
    assert _run(tmp_path, cache) == 21
