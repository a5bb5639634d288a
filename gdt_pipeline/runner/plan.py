"""What a run does, as plain records: from a workflow file, or from a twin's recorded provenance (audits)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..names import identifier
from ..plugins import Registry, StageSpec
from ..workflow import LoadedWorkflow, iter_chain


@dataclass(frozen=True)
class InputPlan:
    """One input to read: where, as what, in which units, and (for audits) the digest it must have."""

    path: Path
    name: str
    kind: str | None = None
    reader: str | None = None
    units: str = "m"
    viewpoints: list | None = None
    sha256: str | None = None
    params: dict[str, Any] | None = None  # the reader's parameters (the input's ``with:``)
    units_given: bool = False  # the workflow wrote ``units:`` on the input (a reader's own units must then agree)


@dataclass(frozen=True)
class StagePlan:
    """One stage to run in an epoch: its position in the chain, record and validated params."""

    index: int
    spec: StageSpec
    params: Any
    id: str | None = None


@dataclass(frozen=True)
class EpochPlan:
    """One epoch to run."""

    id: str
    index: int
    role: str
    inputs: list[InputPlan]
    stages: list[StagePlan]


@dataclass(frozen=True)
class TilingOptions:
    """How to tile an epoch: a tile edge (twin units) or a cap on elements per tile, and the executor to use."""

    executor: str = "serial"
    workers: int | None = None
    tile: float | None = None
    max_elements: int | None = None
    address: str | None = None
    # the tiles' candidates (``tiling.CandidateSink``), the scans' points (``tiling.point_file``), their merged
    # covariances (``tiling.RecentSink``) and the tiles' scores (``tiling.score_sink``) kept in scratch files (TMPDIR),
    # not in memory
    spill: bool = True
    # (epoch id, tile edge) pairs fixed beforehand (an audit replays the sizes a run recorded)
    epoch_sizes: tuple[tuple[str, float], ...] = ()

    @property
    def enabled(self) -> bool:
        """Whether epochs are cut into tiles at all."""
        return self.tile is not None or self.max_elements is not None


@dataclass(frozen=True)
class RunPlan:
    """Everything a run needs, from a workflow file or from a twin's recorded provenance (audits)."""

    name: str
    workflow_path: Path
    workflow_sha256: str
    base_dir: Path
    seed: int
    units: str
    up_axis: str
    epochs: list[EpochPlan]
    tiling: TilingOptions = TilingOptions()
    workflow_text: str | None = None  # recorded in the provenance, so that what ran can be read back


def plan_from_workflow(wf: LoadedWorkflow, registry: Registry) -> RunPlan:
    """The run plan a validated workflow describes."""
    model = wf.model
    epochs = []
    for e_index, epoch in enumerate(model.epochs):
        inputs = [InputPlan(path=wf.input_path(inp), name=inp.name or identifier(Path(inp.path).stem), kind=inp.kind,
                            reader=inp.reader, units=inp.units or model.units, viewpoints=inp.viewpoints,
                            params=inp.with_, units_given=inp.units is not None)
                  for inp in epoch.inputs]
        stages = [StagePlan(index=s_index, spec=registry.get(entry.uses), params=entry.with_, id=entry.id)
                  for s_index, entry in iter_chain(wf, epoch)]
        epochs.append(EpochPlan(id=epoch.id, index=e_index, role=epoch.role, inputs=inputs, stages=stages))
    ex = model.execution
    tiling = TilingOptions(executor=ex.executor, workers=ex.workers, tile=ex.tile, address=ex.address,
                           max_elements=ex.tile_elements)
    return RunPlan(name=model.name, workflow_path=wf.path, workflow_sha256=wf.sha256, base_dir=wf.dir,
                   seed=model.seed, units=model.units, up_axis=model.up_axis, epochs=epochs, tiling=tiling,
                   workflow_text=wf.text)
