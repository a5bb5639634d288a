"""numba for the stages' compiled kernels, configured once: ``from gdt_pipeline.compiled import njit, prange``.

- Threads: numba tries Intel TBB first for ``parallel=True`` loops and warns when the installed one is too old;
  OpenMP (libgomp, which Open3D loads anyway) is what it falls back to, so it is asked for directly.
- Cache: kernels are compiled once and cached on disk (a first run compiles for a few seconds). numba's cache notices
  a change of the function's own file only: a kernel calling a kernel of a sibling module would keep the callee's
  old machine code after that module changed (a pull, a partial upgrade). So each kernel is cached in a directory
  named after the contents of every module of its package, under ``$GDT_CACHE_DIR`` (default
  ``~/.cache/gdt-pipeline``) ``/numba``.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar, overload

import numba
from numba import config, prange

config.THREADING_LAYER = "omp"

__all__ = ["njit", "prange"]


def _cache_root() -> Path:
    return Path(os.environ.get("GDT_CACHE_DIR") or Path.home() / ".cache" / "gdt-pipeline") / "numba"


_PACKAGE_HASH: dict[Path, str] = {}


def _package_hash(folder: Path) -> str:
    """A short hash of the contents of every module in ``folder``."""
    if folder not in _PACKAGE_HASH:
        digest = hashlib.sha256()
        for path in sorted(folder.glob("*.py")):
            digest.update(path.name.encode())
            digest.update(path.read_bytes())
        _PACKAGE_HASH[folder] = digest.hexdigest()[:16]
    return _PACKAGE_HASH[folder]


@contextlib.contextmanager
def _cache_dir_for(fn: Callable[..., Any]) -> Iterator[None]:
    folder = Path(fn.__code__.co_filename).resolve().parent
    before = config.CACHE_DIR
    config.CACHE_DIR = str(_cache_root() / _package_hash(folder))
    try:
        yield
    finally:
        config.CACHE_DIR = before


Kernel = TypeVar("Kernel", bound=Callable[..., Any])


@overload
def njit(fn: Kernel, **options: Any) -> Kernel: ...


@overload
def njit(fn: None = None, **options: Any) -> Callable[[Kernel], Kernel]: ...


def njit(fn: Callable[..., Any] | None = None, **options: Any) -> Any:
    """``numba.njit`` with the on-disk cache described above (``cache`` is always on); a compiled kernel is called
    as the function it compiles, so it keeps that function's signature for type checkers."""
    options.pop("cache", None)

    def compile_cached(f: Callable[..., Any]) -> Any:
        with _cache_dir_for(f):
            return numba.njit(cache=True, **options)(f)

    return compile_cached(fn) if fn is not None else compile_cached
