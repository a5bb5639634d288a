"""Calling one stage: its seeded generator, its run, and the check of what it returned.

Correspondences leave a stage in element order (stable, so each element's candidates keep the order the stage gave
them): the candidate numbering is then the same whether the epoch ran whole or in tiles, and so are the winning
candidate of every element and the pairs a null simulator draws.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from ..errors import GdtError, StageError
from ..plugins import StageContext, StageSpec
from ..slots import valid
from ..types import Correspondences


def element_ordered(corr: Correspondences) -> Correspondences:
    """The same candidates sorted by query element (stable); returned as is when already in that order."""
    if len(corr.element) < 2 or np.all(corr.element[1:] >= corr.element[:-1]):
        return corr
    return corr.take(np.argsort(corr.element, kind="stable"))


@contextlib.contextmanager
def stage_errors(where: str, doing: str = "") -> Iterator[None]:
    """A stage's errors as one paragraph naming where it ran: its own ``GdtError`` kept with the place prefixed,
    anything else a ``StageError`` (interrupts and out-of-memory pass through)."""
    try:
        yield
    except GdtError as exc:
        raise type(exc)(f"{where}: {exc}") from exc
    except (KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:
        raise StageError(f"{where} failed{doing}: {type(exc).__name__}: {exc}") from exc


def run_stage(spec: StageSpec, ctx: StageContext, where: str) -> dict[str, Any]:
    """Run one stage and check that it returned exactly the slots it declares, each of the right type."""
    with stage_errors(where):
        out = spec.run(ctx)
    if not isinstance(out, Mapping):
        raise StageError(f"{where} returned {type(out).__name__}, not a mapping of slots")
    got, want = set(out), set(spec.provides)
    if got != want:
        raise StageError(f"{where} broke its contract: it declares {sorted(want)} but returned {sorted(got)}")
    for slot, value in out.items():
        if not valid(slot, value):
            raise StageError(f"{where} returned a {type(value).__name__} for slot {slot!r}")
    out = dict(out)
    if "correspondences" in out:
        out["correspondences"] = [element_ordered(c) for c in out["correspondences"]]
    return out


def stage_survey(spec: StageSpec, params: Any, slots: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The whole-epoch figures a stage asked for (``StageSpec.survey``), the same for a whole run and every tile."""
    if spec.survey is None:
        return {}
    with stage_errors(where, " surveying the epoch"):
        return dict(spec.survey(params, slots))


def stage_rng(seed: int, epoch_index: int, stage_index: int, tile: int | None = None
              ) -> tuple[np.random.Generator, int]:
    """The stage's own generator and its integer seed, from the workflow seed and the stage's place (and tile: each
    tile draws its own stream, the same whichever executor runs it)."""
    key = (epoch_index, stage_index) if tile is None else (epoch_index, stage_index, tile)
    ss = np.random.SeedSequence(seed, spawn_key=key)
    return np.random.default_rng(ss), int(ss.generate_state(1, dtype=np.uint32)[0])
