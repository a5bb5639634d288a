"""The registry: discovers plugins through the ``gdt_pipeline`` entry points and collects their stages, readers and
tile executors.

Conventions (after conda's and tox's plugin managers): hooks return named records, a duplicate name is an error, an
unknown name errors with "choose one of", a plugin that fails to load is a warning and is skipped, a hook
implementation that matches no hook is an error naming the plugin, and ``GDT_BLOCKED_PLUGINS`` (comma-separated
entry-point or distribution names) keeps named plugins out.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib.metadata as im
import logging
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pluggy
from pydantic import BaseModel, ConfigDict

from ..errors import PluginError
from .specs import (
    BLOCK_ENV,
    ENTRY_POINT_GROUP,
    FAMILIES,
    NAME_RE,
    PROJECT,
    ExecutorSpec,
    GdtSpecs,
    ReaderSpec,
    StageSpec,
)

log = logging.getLogger("gdt.plugins")


@dataclass
class _LoadedPlugin:
    entry_point: str
    dist: str
    version: str
    module: object


def _forbid_extra(params: type[BaseModel]) -> type[BaseModel]:
    """Params models must reject unknown keys, so a misspelt parameter is an error, not a silent default, and NaN or
    infinite numbers (``.inf`` as a σ), which no stage can use, unless the model's config or a field allows them."""
    cfg = params.model_config
    strict = {"extra": "forbid", "allow_inf_nan": cfg.get("allow_inf_nan", False)}
    if all(cfg.get(k) == v for k, v in strict.items()):
        return params
    config: ConfigDict = {**cfg, "extra": "forbid", "allow_inf_nan": bool(strict["allow_inf_nan"])}
    return type(params.__name__, (params,), {"model_config": config, "__module__": params.__module__,
                                             "__doc__": params.__doc__})


def _check_common(spec: StageSpec | ReaderSpec, origin: str) -> str | None:
    if not NAME_RE.match(spec.name):
        return f"{origin}: {spec.family if spec.family == 'reader' else 'stage'} name {spec.name!r} must match " \
               f"[a-z][a-z0-9_]*"
    if not (isinstance(spec.params, type) and issubclass(spec.params, BaseModel)):
        return f"{origin}: {spec.name!r} params must be a pydantic BaseModel subclass"
    return None


def _check_spec(spec: object, origin: str) -> str | None:
    if not isinstance(spec, StageSpec):
        return f"{origin}: hook returned {type(spec).__name__}, not a StageSpec"
    if spec.family not in FAMILIES:
        return (f"{origin}: stage {spec.name!r} has unknown family {spec.family!r} "
                f"(choose one of: {', '.join(FAMILIES)})")
    if not callable(spec.run):
        return f"{origin}: stage {spec.name!r} run is not callable"
    if spec.validate is not None and not callable(spec.validate):
        return f"{origin}: stage {spec.name!r} validate is not callable"
    return _check_common(spec, origin)


def _check_executor(spec: object, origin: str) -> str | None:
    if not isinstance(spec, ExecutorSpec):
        return f"{origin}: gdt_executors returned {type(spec).__name__}, not an ExecutorSpec"
    if not NAME_RE.match(spec.name):
        return f"{origin}: executor name {spec.name!r} must match [a-z][a-z0-9_]*"
    if not callable(spec.open):
        return f"{origin}: executor {spec.name!r} open is not callable"
    return None


def _check_reader(spec: object, origin: str) -> str | None:
    if not isinstance(spec, ReaderSpec):
        return f"{origin}: gdt_readers returned {type(spec).__name__}, not a ReaderSpec"
    if not spec.extensions:
        return f"{origin}: reader {spec.name!r} declares no file extensions"
    if not callable(spec.read):
        return f"{origin}: reader {spec.name!r} read is not callable"
    return _check_common(spec, origin)


class Registry:
    """The stages and readers available in this environment, by unique name."""

    def __init__(self, stages: Mapping[str, StageSpec], plugins: Sequence[_LoadedPlugin], warnings: Sequence[str],
                 manager: pluggy.PluginManager, readers: Mapping[str, ReaderSpec] | None = None,
                 executors: Mapping[str, ExecutorSpec] | None = None) -> None:
        self._stages = dict(sorted(stages.items()))
        self._readers = dict(sorted((readers or {}).items()))
        self._executors = dict(sorted((executors or {}).items()))
        self.plugins = list(plugins)
        self.warnings = list(warnings)
        self.manager = manager

    def __contains__(self, name: str) -> bool:
        return name in self._stages or name in self._readers

    def names(self, family: str | None = None, *, chain_only: bool = False) -> list[str]:
        """Names of stages (and readers), optionally of one family, or all that can appear in a workflow chain."""
        if family == "reader":
            return list(self._readers)
        out = [n for n, s in self._stages.items() if family is None or s.family == family]
        return sorted(out + ([] if chain_only or family is not None else list(self._readers)))

    def stages(self, family: str | None = None) -> list[StageSpec | ReaderSpec]:
        """Stage records (readers first, as family "reader"), sorted by family then name."""
        readers = list(self._readers.values()) if family in (None, "reader") else []
        chain = sorted((s for s in self._stages.values() if family is None or s.family == family),
                       key=lambda s: (FAMILIES.index(s.family), s.name))
        return readers + chain

    def get(self, name: str, family: str | None = None) -> StageSpec:
        """The stage called ``name``; an unknown name raises with a "did you mean" and the names to choose from."""
        spec = self._stages.get(name)
        if spec is not None and (family is None or spec.family == family):
            return spec
        choices = self.names(family) if family else self.names(chain_only=True)
        raise PluginError(unknown_name_message("stage" if family is None else f"{family} stage", name, choices))

    def reader(self, name: str) -> ReaderSpec:
        """The reader called ``name``, or an error naming the installed readers."""
        spec = self._readers.get(name)
        if spec is None:
            raise PluginError(unknown_name_message("reader", name, list(self._readers)))
        return spec

    def executor(self, name: str) -> ExecutorSpec:
        """The tile executor called ``name``, or an error naming the installed executors."""
        spec = self._executors.get(name)
        if spec is None:
            raise PluginError(unknown_name_message("executor", name, list(self._executors)))
        return spec

    def executors(self) -> list[ExecutorSpec]:
        """The installed tile executors, by name."""
        return list(self._executors.values())

    def closest(self, name: str, *, chain_only: bool = True) -> StageSpec | None:
        """The stage whose name is closest to a misspelt one, if any is close."""
        hit = difflib.get_close_matches(name, self.names(chain_only=chain_only), n=1, cutoff=0.6)
        return self._stages.get(hit[0]) if hit else None

    def readers_for(self, path: Path, kind: str | None) -> list[ReaderSpec]:
        """Readers that declare the file's extension and accept this file (and kind, when given)."""
        ext = "".join(path.suffixes[-1:]).lower()
        cands = [s for s in self._readers.values() if ext in s.extensions]
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


def _load_entry_points(pm: pluggy.PluginManager, blocked: set[str], warnings: list[str]
                       ) -> list[tuple[str, str, str, object]]:
    """(plugin name, distribution, version, module) of every entry point that loads; failures become warnings."""
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
        if ep.name in blocked or dist in blocked:
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
        # names (checked later) are what must not clash.
        name = ep.name if ep.name not in used_names else f"{dist}:{ep.name}"
        used_names.add(name)
        sources.append((name, dist, version, module))
    return sources


def _register(pm: pluggy.PluginManager, sources: list[tuple[str, str, str, object]], warnings: list[str]
              ) -> list[_LoadedPlugin]:
    """Register each plugin module with pluggy, then refuse hook implementations that match no hook."""
    loaded = []
    for name, dist, version, module in sources:
        try:
            pm.register(module, name=name)
        except Exception as exc:
            warnings.append(f"plugin {name!r} ({dist}) could not be registered and was skipped: {exc}")
            continue
        loaded.append(_LoadedPlugin(name, dist, version, module))
    try:
        pm.check_pending()
    except pluggy.PluginValidationError as exc:
        name = pm.get_name(exc.plugin) or "?"
        plugin = next((p for p in loaded if p.entry_point == name), None)
        who = f"plugin {name!r}" + (f" ({plugin.dist})" if plugin else "")
        hooks = ", ".join(n for n in dir(GdtSpecs) if n.startswith("gdt_"))
        raise PluginError(f"{who}: {exc}; the hooks of gdt-pipeline are: {hooks}") from None
    return loaded


def _collect(pm: pluggy.PluginManager, hook: str, loaded: list[_LoadedPlugin], warnings: list[str],
             check: Callable[[object, str], str | None], what: str) -> dict[str, Any]:
    """The records every plugin returns from ``hook``, checked, stamped with their plugin, unique by name."""
    by_name = {p.entry_point: p for p in loaded}
    records: dict[str, Any] = {}
    for impl in getattr(pm.hook, hook).get_hookimpls():
        plugin = by_name.get(impl.plugin_name)
        if plugin is None:
            continue
        origin = f"plugin {plugin.entry_point!r} ({plugin.dist})"
        try:
            specs = list(impl.function())
        except Exception as exc:
            warnings.append(f"{origin}: {hook}() raised {type(exc).__name__}: {exc}; its {what}s were skipped")
            continue
        for spec in specs:
            problem = check(spec, origin)
            if problem:
                warnings.append(problem + "; skipped")
                continue
            stamp: dict[str, Any] = {"plugin": plugin.dist, "plugin_version": plugin.version,
                                     "entry_point": plugin.entry_point}
            if hasattr(spec, "params"):
                stamp["params"] = _forbid_extra(spec.params)
            spec = dataclasses.replace(spec, **stamp)
            if spec.name in records:
                other = records[spec.name]
                raise PluginError(
                    f"{what} name {spec.name!r} is provided twice: by plugin {other.entry_point!r} ({other.plugin}) "
                    f"and by plugin {spec.entry_point!r} ({spec.plugin}); {what} names must be unique. "
                    f"Uninstall one, or block it with {BLOCK_ENV}={spec.entry_point}")
            records[spec.name] = spec
    return records


def load_registry(*, blocked: Iterable[str] | None = None, extra: Iterable[tuple[str, object]] = ()) -> Registry:
    """Discover every plugin through the ``gdt_pipeline`` entry points (plus ``extra`` (name, module) pairs)."""
    blocked_names = set(blocked_from_env() if blocked is None else blocked)
    pm = pluggy.PluginManager(PROJECT)
    pm.add_hookspecs(GdtSpecs)
    warnings: list[str] = []
    sources = _load_entry_points(pm, blocked_names, warnings)
    sources += [(name, name, "0", module) for name, module in extra]
    loaded = _register(pm, sources, warnings)
    stages = _collect(pm, "gdt_stages", loaded, warnings, _check_spec, "stage")
    readers = _collect(pm, "gdt_readers", loaded, warnings, _check_reader, "reader")
    executors = _collect(pm, "gdt_executors", loaded, warnings, _check_executor, "executor")
    for name in set(stages) & set(readers):
        raise PluginError(f"the name {name!r} is both a stage ({stages[name].plugin}) and a reader "
                          f"({readers[name].plugin}); names must be unique")
    for w in warnings:
        log.warning(w)
    return Registry(stages, loaded, warnings, pm, readers, executors)
