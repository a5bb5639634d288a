"""Plugin system: pluggy hookspecs, the stage record every plugin returns, and the registry that discovers them.

Every stage, built-in or third-party, arrives the same way: a module listed under the ``gdt_pipeline`` entry-point
group implements the ``gdt_stages`` hook and returns :class:`StageSpec` records. The engine never imports a stage by
name. Conventions (after conda's and tox's plugin managers): hooks return named records, a duplicate stage name is
an error, an unknown name errors with "choose one of", a plugin that fails to load is a warning and is skipped, and
``GDT_BLOCKED_PLUGINS`` (comma-separated entry-point or distribution names) keeps named plugins out.
"""

from __future__ import annotations

import contextlib
import difflib
import importlib.metadata as im
import logging
import os
import re
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, get_args

import numpy as np
import pluggy
from pydantic import BaseModel, ConfigDict

from .errors import PluginError
from .types import EpochInfo

PROJECT = "gdt_pipeline"
ENTRY_POINT_GROUP = "gdt_pipeline"
BLOCK_ENV = "GDT_BLOCKED_PLUGINS"

hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)

Family = Literal["reader", "registrar", "uncertainty", "rov", "correspondence", "distance", "threshold", "fusion"]
FAMILIES: tuple[str, ...] = get_args(Family)
_NAME_RE = re.compile(r"^[a-z][a-z0-9_]*$")

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

    def report(self, **values: Any) -> None:
        """Record figures worth keeping (a tolerance reached, a rate achieved): they go into the epoch's provenance."""
        self.notes.update(values)

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


@dataclass(frozen=True)
class StageSpec:
    """A stage as a plugin declares it.

    ``run(ctx)`` returns a mapping with exactly the ``provides`` slots. ``requires`` must be present before the stage
    runs (checked when the workflow is loaded); ``optional`` slots are handed over when present. ``check`` may add a
    static rule about the slots available (return a message to reject). Readers (family "reader") are not chained:
    the engine picks one per input by ``extensions`` and ``accepts(path, kind)``; their ``run`` gets the slot
    ``request`` (a :class:`ReadRequest`) and provides ``dataset``.
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
    extensions: tuple[str, ...] = ()
    accepts: Callable[[Path, str | None], bool] | None = None
    check: Callable[[frozenset[str]], str | None] | None = None
    plugin: str = ""
    plugin_version: str = ""
    entry_point: str = ""


@dataclass(frozen=True)
class ReadRequest:
    """What a reader is asked to read: one input of an epoch."""

    path: Path
    name: str
    role: str
    kind: str | None
    sha256: str


class GdtSpecs:
    """Hook specifications of gdt-pipeline."""

    @hookspec
    def gdt_stages(self) -> Sequence[StageSpec]:
        """Return the stages this plugin provides."""
        raise NotImplementedError


@dataclass
class _LoadedPlugin:
    entry_point: str
    dist: str
    version: str
    module: object


def _forbid_extra(params: type[BaseModel]) -> type[BaseModel]:
    """Params models must reject unknown keys, so a misspelt parameter is an error, not a silent default."""
    if params.model_config.get("extra") == "forbid":
        return params
    cfg = ConfigDict(**{**params.model_config, "extra": "forbid"})
    return type(params.__name__, (params,), {"model_config": cfg, "__module__": params.__module__})


def _check_spec(spec: object, origin: str) -> str | None:
    if not isinstance(spec, StageSpec):
        return f"{origin}: hook returned {type(spec).__name__}, not a StageSpec"
    if not _NAME_RE.match(spec.name):
        return f"{origin}: stage name {spec.name!r} must match [a-z][a-z0-9_]*"
    if spec.family not in FAMILIES:
        return (f"{origin}: stage {spec.name!r} has unknown family {spec.family!r} "
                f"(choose one of: {', '.join(FAMILIES)})")
    if not (isinstance(spec.params, type) and issubclass(spec.params, BaseModel)):
        return f"{origin}: stage {spec.name!r} params must be a pydantic BaseModel subclass"
    if not callable(spec.run):
        return f"{origin}: stage {spec.name!r} run is not callable"
    if spec.family == "reader" and not spec.extensions:
        return f"{origin}: reader {spec.name!r} declares no file extensions"
    return None


class Registry:
    """The stages available in this environment, by unique name."""

    def __init__(self, stages: Mapping[str, StageSpec], plugins: Sequence[_LoadedPlugin], warnings: Sequence[str],
                 manager: pluggy.PluginManager) -> None:
        self._stages = dict(sorted(stages.items()))
        self.plugins = list(plugins)
        self.warnings = list(warnings)
        self.manager = manager

    def __contains__(self, name: str) -> bool:
        return name in self._stages

    def names(self, family: str | None = None, *, chain_only: bool = False) -> list[str]:
        """Stage names, optionally of one family, or all that can appear in a workflow chain."""
        return [n for n, s in self._stages.items()
                if (family is None or s.family == family) and not (chain_only and s.family == "reader")]

    def stages(self, family: str | None = None) -> list[StageSpec]:
        """Stage records, sorted by family then name."""
        out = [s for s in self._stages.values() if family is None or s.family == family]
        return sorted(out, key=lambda s: (FAMILIES.index(s.family), s.name))

    def get(self, name: str, family: str | None = None) -> StageSpec:
        """The stage called ``name``; an unknown name raises with a "did you mean" and the names to choose from."""
        spec = self._stages.get(name)
        if spec is not None and (family is None or spec.family == family):
            return spec
        choices = self.names(family) if family else self.names(chain_only=True)
        raise PluginError(unknown_name_message("stage" if family is None else f"{family} stage", name, choices))

    def closest(self, name: str, *, chain_only: bool = True) -> StageSpec | None:
        """The stage whose name is closest to a misspelt one, if any is close."""
        hit = difflib.get_close_matches(name, self.names(chain_only=chain_only), n=1, cutoff=0.6)
        return self._stages[hit[0]] if hit else None

    def readers_for(self, path: Path, kind: str | None) -> list[StageSpec]:
        """Readers that declare the file's extension and accept this file (and kind, when given)."""
        ext = "".join(path.suffixes[-1:]).lower()
        cands = [s for s in self.stages("reader") if ext in s.extensions]
        return [s for s in cands if s.accepts is None or s.accepts(path, kind)]


def unknown_name_message(what: str, name: str, choices: Sequence[str]) -> str:
    """'unknown X 'name'; did you mean 'y'? (choose one of: ...)'."""
    hit = difflib.get_close_matches(name, list(choices), n=1, cutoff=0.6)
    mean = f"; did you mean {hit[0]!r}?" if hit else ""
    return f"unknown {what} {name!r}{mean} (choose one of: {', '.join(sorted(choices)) or 'none installed'})"


def blocked_from_env() -> set[str]:
    """Plugin names blocked through ``GDT_BLOCKED_PLUGINS``."""
    return {p.strip() for p in os.environ.get(BLOCK_ENV, "").split(",") if p.strip()}


def _entry_points() -> Iterable[im.EntryPoint]:
    return im.entry_points(group=ENTRY_POINT_GROUP)


def load_registry(*, blocked: Iterable[str] | None = None, extra: Iterable[tuple[str, object]] = ()) -> Registry:
    """Discover every plugin through the ``gdt_pipeline`` entry points (plus ``extra`` (name, module) pairs)."""
    blocked_names = set(blocked_from_env() if blocked is None else blocked)
    pm = pluggy.PluginManager(PROJECT)
    pm.add_hookspecs(GdtSpecs)
    warnings: list[str] = []
    loaded: list[_LoadedPlugin] = []
    sources: list[tuple[str, str, str, object]] = []
    seen_eps: set[tuple[str, str, str]] = set()
    used_names: set[str] = set()
    for ep in _entry_points():
        dist = ep.dist.name if ep.dist is not None else "?"
        version = ep.dist.version if ep.dist is not None else "?"
        if (dist, ep.name, ep.value) in seen_eps:
            # The same distribution can be visible twice (e.g. an editable install plus a stale egg-info).
            continue
        seen_eps.add((dist, ep.name, ep.value))
        if ep.name in blocked_names or dist in blocked_names:
            pm.set_blocked(ep.name)
            log.info("plugin %s (%s) blocked by %s", ep.name, dist, BLOCK_ENV)
            continue
        try:
            module = ep.load()
        except Exception as exc:  # a broken third-party plugin must not take the tool down
            warnings.append(f"plugin {ep.name!r} ({dist} {version}) failed to load and was skipped: "
                            f"{type(exc).__name__}: {exc}")
            continue
        # Two distributions may pick the same entry-point name; pluggy needs unique plugin names, and the stage
        # names (checked below) are what must not clash.
        name = ep.name if ep.name not in used_names else f"{dist}:{ep.name}"
        used_names.add(name)
        sources.append((name, dist, version, module))
    for name, module in extra:
        sources.append((name, name, "0", module))
    for name, dist, version, module in sources:
        try:
            pm.register(module, name=name)
        except Exception as exc:
            warnings.append(f"plugin {name!r} ({dist}) could not be registered and was skipped: {exc}")
            continue
        loaded.append(_LoadedPlugin(name, dist, version, module))
    by_name = {p.entry_point: p for p in loaded}
    stages: dict[str, StageSpec] = {}
    for impl in pm.hook.gdt_stages.get_hookimpls():
        plugin = by_name.get(impl.plugin_name)
        if plugin is None:
            continue
        origin = f"plugin {plugin.entry_point!r} ({plugin.dist})"
        try:
            records = list(impl.function())
        except Exception as exc:
            warnings.append(f"{origin}: gdt_stages() raised {type(exc).__name__}: {exc}; its stages were skipped")
            continue
        for spec in records:
            problem = _check_spec(spec, origin)
            if problem:
                warnings.append(problem + "; skipped")
                continue
            spec = StageSpec(**{**spec.__dict__, "params": _forbid_extra(spec.params), "plugin": plugin.dist,
                                "plugin_version": plugin.version, "entry_point": plugin.entry_point})
            if spec.name in stages:
                other = stages[spec.name]
                raise PluginError(
                    f"stage name {spec.name!r} is provided twice: by plugin {other.entry_point!r} ({other.plugin}) "
                    f"and by plugin {spec.entry_point!r} ({spec.plugin}); stage names must be unique. "
                    f"Uninstall one, or block it with {BLOCK_ENV}={spec.entry_point}")
            stages[spec.name] = spec
    for w in warnings:
        log.warning(w)
    return Registry(stages, loaded, warnings, pm)
