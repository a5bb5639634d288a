"""The provenance of an epoch as typed records: the runner writes them into each layer's ``customLayerData`` and
``gdt.lock``, the audit reads them back to re-run the epoch. Their JSON form (``to_dict``) is what the twin stores;
``from_dict`` also reads twins written before a field existed (it takes the field's default)."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from .plugins import StageSpec

PACKAGES = ("gdt-pipeline", "numpy", "scipy", "open3d-cpu", "open3d", "usd-core", "trimesh", "pydantic", "pluggy",
            "pymeshlab", "laspy")
# The fields of a stage record that gdt.lock repeats per stage.
LOCK_STAGE_FIELDS = ("uses", "plugin", "plugin_version", "version", "params", "seed", "cache_key")


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def cache_key(spec: StageSpec, params: Mapping[str, Any], input_digests: list[str], upstream: list[str]) -> str:
    """sha256 of plugin, stage name and version, validated params, input digests and upstream keys."""
    payload = {"plugin": spec.plugin, "plugin_version": spec.plugin_version, "stage": spec.name,
               "version": spec.version, "params": params, "inputs": input_digests, "upstream": upstream}
    return hashlib.sha256(_canonical(payload).encode()).hexdigest()


def package_versions() -> dict[str, str]:
    """Versions of the packages that shape results."""
    out = {}
    for name in PACKAGES:
        with contextlib.suppress(PackageNotFoundError):
            out[name] = version(name)
    return out


def _known(cls: type, data: Mapping[str, Any]) -> dict[str, Any]:
    """The entries of ``data`` that are fields of ``cls`` (older or newer twins may carry others)."""
    names = {f.name for f in dataclasses.fields(cls)}
    return {k: v for k, v in data.items() if k in names}


@dataclass(frozen=True)
class WorkflowRecord:
    """Which workflow made the twin, and where its inputs are relative to the twin."""

    path: str = "workflow.yaml"
    sha256: str = ""
    name: str = "audit"
    dir_from_twin: str | None = None
    units: str = "m"
    up_axis: str = "Z"
    text: str | None = None  # the workflow as it ran (``gdt add`` writes one; a file may change after the run)


@dataclass(frozen=True)
class InputRecord:
    """One input file of an epoch as it was read."""

    path: str
    sha256: str
    name: str
    kind: str = "points"
    kind_hint: str | None = None
    reader: str | None = None
    units: str = "m"
    scale: float = 1.0
    viewpoints: list | None = None
    elements: int = 0
    notes: dict[str, Any] = field(default_factory=dict)
    # per dataset the file gave (one, or one per scan or part): name, kind, elements, meta (part name, IFC GlobalId),
    # and the station it was given: pose {source, origin, position, ...} (pose file, file header or workflow)
    datasets: list[dict[str, Any]] = field(default_factory=list)
    params: dict[str, Any] | None = None  # the reader's parameters (the input's ``with:``), as validated


@dataclass(frozen=True)
class StageRecord:
    """One stage as it ran in an epoch: what it was, with which params and seed, its cache key, time and report."""

    index: int
    uses: str
    id: str | None = None
    family: str = ""
    version: str = ""
    plugin: str = ""
    plugin_version: str = ""
    entry_point: str = ""
    params: dict[str, Any] = field(default_factory=dict)
    seed_spawn_key: list[int] = field(default_factory=list)
    seed: int = 0
    requires: list[str] = field(default_factory=list)
    provides: list[str] = field(default_factory=list)
    cache_key: str = ""
    seconds: float = 0.0
    report: dict[str, Any] = field(default_factory=dict)

    def lock_entry(self) -> dict[str, Any]:
        """What gdt.lock keeps of this stage."""
        return {k: getattr(self, k) for k in LOCK_STAGE_FIELDS}


@dataclass(frozen=True)
class EpochRecord:
    """Which epoch of the workflow a layer holds."""

    id: str
    index: int
    role: str


@dataclass(frozen=True)
class EpochProvenance:
    """Everything needed to re-run one epoch and to see how it was made."""

    gdt_pipeline: str
    workflow: WorkflowRecord
    epoch: EpochRecord
    seed: int
    inputs: list[InputRecord]
    stages: list[StageRecord]
    registration: dict[str, Any] | None = None
    packages: dict[str, str] = field(default_factory=dict)
    python: str = ""
    started: str = ""
    finished: str = ""
    counts: dict[str, int] = field(default_factory=dict)
    epoch_key: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The JSON form the twin stores (it sorts the keys)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> EpochProvenance:
        """Read a stored record (missing fields take their defaults)."""
        values = _known(cls, data)
        values["workflow"] = WorkflowRecord(**_known(WorkflowRecord, data.get("workflow", {})))
        values["epoch"] = EpochRecord(**_known(EpochRecord, data["epoch"]))
        values["inputs"] = [InputRecord(**_known(InputRecord, r)) for r in data.get("inputs", [])]
        values["stages"] = [StageRecord(**_known(StageRecord, r)) for r in data.get("stages", [])]
        values.setdefault("gdt_pipeline", "?")
        values.setdefault("seed", 0)
        return cls(**values)

    def lock_entry(self) -> dict[str, Any]:
        """What gdt.lock keeps of this epoch."""
        return {"id": self.epoch.id, "inputs": [dataclasses.asdict(r) for r in self.inputs],
                "epoch_key": self.epoch_key, "stages": [s.lock_entry() for s in self.stages]}
