"""numba for the stages' compiled kernels, configured once: ``from gdt_pipeline.compiled import njit, prange``.

numba tries Intel TBB first for ``parallel=True`` loops and warns when the installed one is too old; OpenMP (libgomp,
which Open3D loads anyway) is what it falls back to, so it is asked for directly.
"""

from __future__ import annotations

from numba import config, njit, prange

config.THREADING_LAYER = "omp"

__all__ = ["njit", "prange"]
