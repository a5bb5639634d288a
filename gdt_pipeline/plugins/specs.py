"""Plugin system: pluggy hookspecs and the records every plugin returns.

Every stage, built-in or third-party, arrives the same way: a module listed under the ``gdt_pipeline`` entry-point
group implements the ``gdt_stages`` hook and returns :class:`StageSpec` records; file readers are their own
extension kind, returned by the ``gdt_readers`` hook as :class:`ReaderSpec` records. The engine never imports a
stage by name. A hook implementation whose name matches no hook (a misspelt ``gdt_stage``) is an error naming the
plugin, not a plugin that silently provides nothing.

This module holds what a plugin sees: the hook markers, the records (:class:`StageSpec`, :class:`ReaderSpec`), the
context a stage runs in. ``registry`` discovers the plugins.
"""

from __future__ import annotations

import contextlib
import logging
import re
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, get_args

import numpy as np
import pluggy
from pydantic import BaseModel

from ..errors import PluginError
from ..geometry.normals import knn_reach, within_dense_cells
from ..types import Dataset, EpochInfo

PROJECT = "gdt_pipeline"
ENTRY_POINT_GROUP = "gdt_pipeline"
BLOCK_ENV = "GDT_BLOCKED_PLUGINS"

hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)

Family = Literal["registrar", "uncertainty", "rov", "correspondence", "distance", "threshold", "fusion"]
FAMILIES: tuple[str, ...] = get_args(Family)
NAME_RE = re.compile(r"^[a-z][a-z0-9_]*$")

log = logging.getLogger("gdt.plugins")


class ProgressTask(Protocol):
    """Advance callback of a progress task."""

    def __call__(self, advance: float = 1.0) -> None:
        """Advance the task by ``advance`` units."""


class Progress(Protocol):
    """What a stage uses to report progress on long work; the runner shows it, tests ignore it."""

    def task(self, description: str, total: float) -> contextlib.AbstractContextManager[ProgressTask]:
        """A progress task of ``total`` units, advanced through the callback the context yields."""


class NullProgress:
    """Progress that shows nothing (tests, library use, ``--quiet``)."""

    @contextlib.contextmanager
    def task(self, description: str, total: float) -> Iterator[ProgressTask]:
        """Yield a callback that does nothing."""
        yield lambda advance=1.0: None


@dataclass(frozen=True)
class TileBounds:
    """The tile a stage runs on: its core box, and the box (core plus halo) inside which its inputs are complete."""

    core_lower: np.ndarray
    core_upper: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    def in_core(self, positions: np.ndarray) -> np.ndarray:
        """Per position, whether it lies in the core box (bounds included)."""
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        return np.asarray(np.all((pos >= self.core_lower) & (pos <= self.core_upper), axis=1), dtype=bool)

    def shortfall(self, positions: np.ndarray, radii: np.ndarray | float) -> float:
        """How much farther the halo must reach for every core element's sphere of ``radii`` to lie inside it."""
        pos = np.asarray(positions, dtype=np.float64)
        core = self.in_core(pos)
        if not core.any():
            return 0.0
        r = np.broadcast_to(np.asarray(radii, dtype=np.float64), (len(pos),))[core]
        room = np.minimum((pos[core] - self.lower).min(axis=1), (self.upper - pos[core]).min(axis=1))
        return float(max(0.0, np.max(r - room)))

    def proven_knn(self, points: np.ndarray, k: int) -> np.ndarray:
        """Per point, whether its ``k``-nearest neighbourhood provably lies inside the halo without a search: a core
        point in a grid cube holding k points, the cube's diagonal no longer than every core point's room to the
        halo's edge (outside the core nothing needs proving)."""
        pos = np.asarray(points, dtype=np.float64)
        core = self.in_core(pos)
        if not core.any():
            return np.ones(len(pos), dtype=bool)
        room = np.minimum((pos[core] - self.lower).min(axis=1), (self.upper - pos[core]).min(axis=1))
        # shrunk a hair so that rounding in the cell arithmetic cannot put a neighbour beyond the room
        proven = within_dense_cells(pos, k, float(room.min()) * (1 - 1e-9) / np.sqrt(3.0), self.lower)
        return np.asarray(proven | ~core, dtype=bool)


@dataclass(frozen=True)
class StageContext:
    """What a stage's ``run`` receives: its validated params, the slots it declared, a seeded rng, and services."""

    stage: StageSpec
    params: Any
    slots: Mapping[str, Any]
    epoch: EpochInfo
    rng: np.random.Generator
    seed: int
    log: logging.Logger
    progress: Progress = field(default_factory=NullProgress)
    notes: dict[str, Any] = field(default_factory=dict)
    tile: TileBounds | None = None
    shortfalls: list[float] = field(default_factory=list)
    survey: Mapping[str, Any] = field(default_factory=dict)

    def report(self, **values: Any) -> None:
        """Record figures worth keeping (a tolerance reached, a rate achieved): they go into the epoch's provenance."""
        self.notes.update(values)

    def kept(self, positions: np.ndarray) -> np.ndarray | None:
        """Per element at ``positions``, whether its result is kept: in a tile, those in its core grown by the later
        stages' reach (a stage may skip work for the rest, which only serve as neighbours); elsewhere None (all)."""
        return None if self.tile is None else self.tile.in_core(positions)

    def neighbourhoods(self, positions: np.ndarray, radii: np.ndarray | float) -> None:
        """Declare that the result at each of ``positions`` used data within ``radii`` of it (a k-nearest search's
        reach, known only once searched). In a tile whose halo was too narrow for a core element, the runner runs
        the tile again with a wider one, so tiled results stay those of the whole epoch; elsewhere nothing happens."""
        if self.tile is not None:
            self.shortfalls.append(self.tile.shortfall(positions, radii))

    def k_nearest(self, points: np.ndarray, k: int) -> None:
        """Declare that the result at each of ``points`` used its ``k`` nearest points (PCA normals): in a tile, how
        far each neighbourhood reached is searched and declared as ``neighbourhoods``; elsewhere nothing happens."""
        if self.tile is None:
            return
        unsure = ~self.tile.proven_knn(points, k)
        self.neighbourhoods(points[unsure], knn_reach(points, k, unsure))

    def __getitem__(self, name: str) -> Any:
        """The value of a required slot."""
        try:
            return self.slots[name]
        except KeyError:
            st = self.stage
            raise PluginError(f"stage {st.name!r} asked for slot {name!r}, which it did not declare "
                              f"(requires: {list(st.requires)}, optional: {list(st.optional)})") from None

    def get(self, name: str, default: Any = None) -> Any:
        """The value of an optional slot, or ``default`` when no earlier stage provided it."""
        return self.slots.get(name, default)


# A stage's reach: one distance for the epoch, or per recent dataset one per element (``StageSpec``).
ReachFn = Callable[[Any, Mapping[str, Any]], "float | Sequence[np.ndarray]"]


@dataclass(frozen=True)
class StageSpec:
    """A stage as a plugin declares it.

    ``run(ctx)`` returns a mapping with exactly the ``provides`` slots. ``requires`` must be present before the stage
    runs (checked when the workflow is loaded); ``optional`` slots are handed over when present. ``check`` may add a
    static rule about the slots available (return a message to reject). ``validate(params, workflow_dir)`` may check
    what the params name outside the workflow (files: present, readable, well-formed) before anything runs: it returns
    ``(key, message)`` problems, ``key`` the parameter's dotted path under ``with`` (e.g. ``parts.0.path``).

    Tiling (``docs/scale.md``): a stage with ``tiling="tile"`` promises that its output for a recent element depends
    only on data within ``reach(params, slots)`` of that element (0 when ``reach`` is None), so the runner may run it
    on one 3-D tile plus a halo at a time and keep the core. ``reach`` returns one distance for the epoch, or one
    array per recent dataset with each element's reach (what it would be if every element were like this one): a
    tile's halo is then the largest over the elements near its core (``runner.halos``). Such a stage provides only
    ``recent`` (uncertainty attached, geometry untouched), ``correspondences``, ``scores`` or ``change``.
    ``survey(params, slots)`` gives the whole-epoch figures a stage needs in every tile alike (a mean facet area):
    computed once on the epoch's slots, whole run or tiled, and handed over as ``ctx.survey``. ``finish(ctx)``, when
    given, runs once on the whole epoch's merged slots after a tiled run and returns slots to replace (e.g. a null
    simulator over every pair); a stage whose output cannot travel between processes (closures) rebuilds it there.
    """

    name: str
    family: Family
    version: str
    params: type[BaseModel]
    run: Callable[[StageContext], Mapping[str, Any]]
    requires: tuple[str, ...] = ()
    provides: tuple[str, ...] = ()
    optional: tuple[str, ...] = ()
    description: str = ""
    check: Callable[[frozenset[str]], str | None] | None = None
    validate: Callable[[Any, Path], Sequence[tuple[str, str]]] | None = None
    tiling: Literal["epoch", "tile"] = "epoch"
    reach: ReachFn | None = None
    survey: Callable[[Any, Mapping[str, Any]], Mapping[str, Any]] | None = None
    finish: Callable[[StageContext], Mapping[str, Any]] | None = None
    plugin: str = ""
    plugin_version: str = ""
    entry_point: str = ""


# The slots a stage of each family reads and writes unless it says otherwise (``family_stage``).
FAMILY_SLOTS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "registrar": (("recent", "reference"), ("recent", "registration")),
    "uncertainty": (("recent",), ("recent",)),
    "rov": (("recent",), ("rov",)),
    "correspondence": (("recent", "reference"), ("correspondences",)),
    "distance": (("recent", "reference", "correspondences"), ("scores",)),
    "threshold": (("scores",), ("change",)),
    "fusion": (("recent",), ("composite",)),
}
Run = Callable[[StageContext], Mapping[str, Any]]


def family_stage(family: Family, *, name: str, version: str, params: type[BaseModel], run: Run,
                 description: str = "", requires: tuple[str, ...] | None = None,
                 provides: tuple[str, ...] | None = None, optional: tuple[str, ...] = (),
                 check: Callable[[frozenset[str]], str | None] | None = None,
                 validate: Callable[[Any, Path], Sequence[tuple[str, str]]] | None = None,
                 tiling: Literal["epoch", "tile"] = "epoch",
                 reach: ReachFn | None = None,
                 survey: Callable[[Any, Mapping[str, Any]], Mapping[str, Any]] | None = None,
                 finish: Callable[[StageContext], Mapping[str, Any]] | None = None) -> StageSpec:
    """A stage of ``family`` that reads and writes the family's usual slots (``FAMILY_SLOTS``; ``requires`` and
    ``provides`` say otherwise where it differs): what a stage module declares of itself, one call per stage."""
    usual_requires, usual_provides = FAMILY_SLOTS[family]
    return StageSpec(name=name, family=family, version=version, params=params, run=run,
                     requires=usual_requires if requires is None else requires,
                     provides=usual_provides if provides is None else provides, optional=optional,
                     description=description, check=check, validate=validate, tiling=tiling, reach=reach,
                     survey=survey, finish=finish)


@dataclass(frozen=True)
class ReadRequest:
    """What a reader is asked to read: one input of an epoch, with the reader's validated params."""

    path: Path
    name: str
    role: str
    kind: str | None
    sha256: str
    params: Any = None
    notes: dict[str, Any] = field(default_factory=dict)

    def report(self, **values: Any) -> None:
        """Record what reading did to the data (e.g. degenerate facets dropped): it goes into the input's provenance."""
        self.notes.update(values)


@dataclass(frozen=True)
class BoxRead:
    """The points of one box of an input: their element numbers (as the whole read numbers them, ascending), their
    coordinates in the file's units and the per-point fields the whole read would give them."""

    elements: np.ndarray
    points: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)


class BoxSource(Protocol):
    """An input opened for reading one box at a time (``ReaderSpec.boxes``), without ever holding the whole file:
    ``count`` elements (after the reader's filters) within ``lower``..``upper`` (file units)."""

    count: int
    lower: np.ndarray
    upper: np.ndarray

    def read_box(self, lower: np.ndarray, upper: np.ndarray) -> BoxRead:
        """The elements inside the closed box [lower, upper], exactly those the whole read puts there."""

    def close(self) -> None:
        """Let go of the file."""


@dataclass(frozen=True)
class ReaderSpec:
    """A file reader as a plugin declares it (hook ``gdt_readers``).

    Readers are not chained: the engine picks one per input by ``extensions`` and ``accepts(path, kind)`` (or the
    input's ``reader:``) and calls ``read(request)``, which returns a :class:`~gdt_pipeline.types.Dataset`, or a
    list of them for a file of several scans or parts (each named by its part: the engine names it
    ``<input>_<part>`` and keeps the part's name in ``meta``). A reader that knows the station of a scan (an E57
    header) sets ``Dataset.pose`` with source ``"file_header"``. The engine then checks the geometry, applies the
    unit scale and settles each dataset's station (pose file, file header, ``viewpoints:``, in that order).
    """

    name: str
    version: str
    extensions: tuple[str, ...]
    read: Callable[[ReadRequest], Dataset | list[Dataset]]
    params: type[BaseModel] = BaseModel
    accepts: Callable[[Path, str | None], bool] | None = None
    # An input opened for box reads (the same request, the same elements as ``read``): what lets a tile read only
    # its own points of a large file. None, or returning None for a file, where the format (or that file: an ASCII
    # PLY) has no way to find a box's points but reading them all.
    boxes: Callable[[ReadRequest], BoxSource | None] | None = None
    description: str = ""
    plugin: str = ""
    plugin_version: str = ""
    entry_point: str = ""

    # A reader is listed beside the stages (``gdt plugins``) with the same columns.
    family = "reader"
    requires: tuple[str, ...] = ()
    provides: tuple[str, ...] = ("dataset",)
    optional: tuple[str, ...] = ()


class TileExecutor(Protocol):
    """Runs tile tasks somewhere (this process, a pool, a cluster) and hands back their results in task order."""

    dashboard: str | None

    def map(self, fn: Callable[[Any], Any], tasks: Iterable[Any],
            done: Callable[[int, Any], None] | None = None) -> list[Any]:
        """``fn(task)`` for every task (an iterable, pulled as workers free up); ``done(i, result)`` as each one
        finishes (any order); the results in task order."""


@dataclass(frozen=True)
class ExecutorOptions:
    """What the user asked of an executor: workers (None: one per core) and a cluster address (Dask)."""

    workers: int | None = None
    address: str | None = None


@dataclass(frozen=True)
class ExecutorSpec:
    """An executor of tiles as a plugin declares it (hook ``gdt_executors``).

    ``open(options)`` is a context manager yielding a :class:`TileExecutor`; it owns the workers it starts. An
    executor that runs tasks in other processes (``in_process`` False) receives tasks that name their stages, and
    each worker finds them through its own registry, so every plugin must be installed where the workers run.
    """

    name: str
    version: str
    open: Callable[[ExecutorOptions], contextlib.AbstractContextManager[TileExecutor]]
    in_process: bool = False
    description: str = ""
    plugin: str = ""
    plugin_version: str = ""
    entry_point: str = ""


class GdtSpecs:
    """Hook specifications of gdt-pipeline."""

    @hookspec
    def gdt_stages(self) -> Sequence[StageSpec]:
        """Return the stages this plugin provides."""
        raise NotImplementedError

    @hookspec
    def gdt_readers(self) -> Sequence[ReaderSpec]:
        """Return the file readers this plugin provides."""
        raise NotImplementedError

    @hookspec
    def gdt_executors(self) -> Sequence[ExecutorSpec]:
        """Return the tile executors this plugin provides."""
        raise NotImplementedError


