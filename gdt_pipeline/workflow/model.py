"""The workflow model: epochs, inputs and the chain, joined with every stage's params model from the registry."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, create_model, field_validator

from ..names import Units
from ..plugins import Registry, StageSpec

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Identifier = Annotated[str, Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$", max_length=64)]


class StrictModel(BaseModel):
    """Unknown keys are errors: a misspelt key must not become a silent default; no number may be NaN or infinite."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True, allow_inf_nan=False)


class InputSpec(StrictModel):
    """One input file of an epoch."""

    path: str = Field(description="File path, relative to the workflow file.")
    name: Identifier | None = Field(None, description="Dataset name in the twin; default: the file stem.")
    kind: Literal["mesh", "points"] | None = Field(None, description="Force mesh or point reading (PLY can be both).")
    units: Units | None = Field(None, description="Units the file is written in; default: the workflow's units.")
    reader: str | None = Field(None, description="Reader stage to use; default: chosen by file extension.")
    viewpoints: list[Vec3] | None = Field(None, description="Sensor positions (in the file's units), if known; a pose "
                                                            "file beside the scan and the file's own header (E57) "
                                                            "come first (docs/formats.md).")
    with_: dict[str, Any] | None = Field(None, alias="with", description="The reader's parameters (e.g. LAS "
                                                                         "`classes`, STEP `tolerance`, E57 `scans`).")


class EpochSpec(StrictModel):
    """One epoch: its id, role and input files."""

    id: Identifier
    role: Literal["as-designed", "as-is"]
    inputs: list[InputSpec] = Field(min_length=1)
    description: str = ""


class StageEntryBase(StrictModel):
    """Fields every chain entry has besides ``uses`` and ``with``."""

    id: Identifier | None = Field(None, description="Optional label for logs and provenance.")
    role: Literal["as-designed", "as-is"] | None = Field(None, description="Run only in epochs of this role.")
    epochs: list[str] | None = Field(None, description="Run only in these epochs (ids).")

    def applies_to(self, epoch: EpochSpec) -> bool:
        """Whether this chain entry runs in ``epoch``."""
        return (self.role is None or self.role == epoch.role) and (self.epochs is None or epoch.id in self.epochs)


class ExecutionSpec(StrictModel):
    """How the run is spread: 3-D tiles and the executor that runs them (``docs/scale.md``); the command line's
    ``--executor``, ``--workers``, ``--tile`` and ``--address`` override these."""

    executor: str = Field("serial", description="Tile executor: serial, processes (a local pool) or dask.")
    workers: int | None = Field(None, ge=1, description="Worker processes (default: one per core).")
    tile: float | None = Field(None, gt=0, description="Tile edge in twin units; default: no tiles (unless "
                                                       "tile_elements is given).")
    tile_elements: int | None = Field(None, ge=1000, description="Largest number of recent elements in one tile's "
                                                                 "core: the tile edge is halved until it fits.")
    address: str | None = Field(None, description="Address of a running Dask scheduler (tcp://host:8786); "
                                                  "default: a local cluster.")


class WorkflowBase(StrictModel):
    """Fields of a workflow file other than the chain."""

    name: str = Field(min_length=1)
    description: str = ""
    twin: str = Field(description="Twin folder to write, relative to the workflow file.")
    seed: int = Field(0, ge=0, lt=2**63, description="Seed of every random draw of the run.")
    units: Units = Field("m", description="Units of the twin.")
    up_axis: Literal["Y", "Z"] = "Z"
    epochs: list[EpochSpec] = Field(min_length=1)
    execution: ExecutionSpec = Field(default_factory=ExecutionSpec)

    @field_validator("epochs")
    @classmethod
    def _unique_epoch_ids(cls, epochs: list[EpochSpec]) -> list[EpochSpec]:
        ids = [e.id for e in epochs]
        dups = sorted({i for i in ids if ids.count(i) > 1})
        if dups:
            raise ValueError(f"epoch ids must be unique; repeated: {', '.join(dups)}")
        return epochs


@dataclass(frozen=True)
class LoadedWorkflow:
    """A validated workflow with where it came from."""

    path: Path
    sha256: str
    model: Any  # an instance of the registry-built Workflow model
    text: str

    @property
    def dir(self) -> Path:
        """Folder the workflow's relative paths are resolved against."""
        return self.path.parent

    def twin_path(self) -> Path:
        """The twin folder the workflow names, resolved."""
        return (self.dir / self.model.twin).resolve()

    def input_path(self, inp: InputSpec) -> Path:
        """An input's file path, resolved."""
        return (self.dir / inp.path).resolve()


def entry_model(spec: StageSpec) -> type[BaseModel]:
    return create_model(
        f"Stage_{spec.name}",
        __base__=StageEntryBase,
        __doc__=f"{spec.family} stage {spec.name!r} ({spec.plugin} {spec.plugin_version}). {spec.description}".strip(),
        uses=(Literal[spec.name], Field(description=spec.description or spec.name)),  # type: ignore[valid-type]
        # an empty mapping validated like a given one, so a stage whose params need a key is told so at its entry
        with_=(spec.params, Field(default_factory=dict, alias="with", validate_default=True)),
    )


def workflow_model(registry: Registry) -> type[BaseModel]:
    """The pydantic model of a workflow file for the stages installed now (a discriminated union on ``uses``)."""
    entries = [entry_model(registry.get(n)) for n in registry.names(chain_only=True)]
    if not entries:
        entry_type: Any = StageEntryBase
    elif len(entries) == 1:
        entry_type = entries[0]
    else:
        entry_type = Annotated[Union[tuple(entries)], Field(discriminator="uses")]  # noqa: UP007
    return create_model("Workflow", __base__=WorkflowBase, stages=(list[entry_type], Field(min_length=1)))


def json_schema(registry: Registry) -> dict[str, Any]:
    """JSON Schema of workflow files, for editors (``# yaml-language-server: $schema=...``)."""
    schema = workflow_model(registry).model_json_schema(by_alias=True)
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "gdt-pipeline workflow"
    return schema


# ---------------------------------------------------------------------------------------------------------------------
# YAML with positions


