"""Plans from what a twin recorded: an epoch's stages and inputs as its provenance names them (audits re-run them;
``gdt add`` runs a recorded chain on a new scan)."""

from __future__ import annotations

from pathlib import Path

from pydantic import ValidationError

from twin_store import TwinStore

from ..errors import GdtError, PluginError
from ..plugins import Registry
from ..provenance import EpochProvenance, StageRecord
from .inputs import sha256_file
from .plan import InputPlan, StagePlan


def recorded_stage(eid: str, rec: StageRecord, registry: Registry, warnings: list[str]) -> StagePlan:
    """The installed stage a record names, with its recorded params; a version change is a warning."""
    try:
        spec = registry.get(rec.uses)
    except PluginError as exc:
        raise GdtError(f"epoch {eid} was made with stage {rec.uses!r} ({rec.plugin} {rec.plugin_version}), which "
                       f"is not installed: {exc}") from exc
    if (spec.plugin_version, spec.version) != (rec.plugin_version, rec.version):
        warnings.append(f"epoch {eid}: stage {spec.name!r} was made with {rec.plugin} {rec.plugin_version} (stage "
                        f"{rec.version}); installed is {spec.plugin} {spec.plugin_version} (stage {spec.version})")
    try:
        params = spec.params.model_validate(rec.params)
    except ValidationError as exc:
        raise GdtError(f"epoch {eid}: the recorded params of stage {spec.name!r} no longer validate against the "
                       f"installed version: {exc.errors(include_url=False)}") from exc
    return StagePlan(index=rec.index, spec=spec, params=params, id=rec.id)


def inputs_dir(store: TwinStore, prov: EpochProvenance, base_dir: Path | None) -> Path:
    """Where an epoch's inputs were: ``base_dir`` when given, else the folder its provenance names relative to the
    twin (each epoch its own: appends may come from other folders)."""
    if base_dir is not None:
        return base_dir.resolve()
    if prov.workflow.dir_from_twin is None:
        raise GdtError(f"{store.path}: the provenance of epoch {prov.epoch.id} does not say where its inputs were "
                       f"(made by an older gdt); pass --inputs-dir")
    return (store.path / prov.workflow.dir_from_twin).resolve()


def recorded_inputs(prov: EpochProvenance, base: Path, problems: list[str]) -> list[InputPlan]:
    """The inputs an epoch read, located under ``base``; a missing or changed file is added to ``problems``."""
    inputs = []
    for rec in prov.inputs:
        path = base / rec.path
        if not path.is_file():
            problems.append(f"input {rec.path} is missing (looked at {path}; recorded sha256 {rec.sha256[:16]}...)")
        elif (digest := sha256_file(path)) != rec.sha256:
            problems.append(f"input {rec.path} has changed: sha256 {digest} is not the recorded {rec.sha256}")
        inputs.append(InputPlan(path=path, name=rec.name, kind=rec.kind_hint, reader=rec.reader, units=rec.units,
                                viewpoints=rec.viewpoints, sha256=rec.sha256, params=rec.params))
    return inputs
