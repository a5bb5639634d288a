"""The runner: plans from workflow files (or from a twin's provenance), reading inputs, running the chain epoch by
epoch and writing the twin (see ``execute`` for reproducibility, traceability and safety)."""

from ..provenance import cache_key, package_versions
from .execute import (
    LOCK_NAME,
    EpochSummary,
    Reporter,
    RunResult,
    execute_plan,
    run_workflow,
)
from .inputs import check_dataset, read_dataset, read_datasets, read_input, sha256_file
from .plan import EpochPlan, InputPlan, RunPlan, StagePlan, TilingOptions, plan_from_workflow
from .poses import pose_file_for, read_pose_file, resolve_poses
from .stage_call import element_ordered, run_stage, stage_rng

__all__ = [
    "LOCK_NAME",
    "EpochPlan",
    "EpochSummary",
    "InputPlan",
    "Reporter",
    "RunPlan",
    "RunResult",
    "StagePlan",
    "TilingOptions",
    "cache_key",
    "check_dataset",
    "element_ordered",
    "execute_plan",
    "package_versions",
    "plan_from_workflow",
    "pose_file_for",
    "read_dataset",
    "read_datasets",
    "read_input",
    "read_pose_file",
    "resolve_poses",
    "run_stage",
    "run_workflow",
    "sha256_file",
    "stage_rng",
]
