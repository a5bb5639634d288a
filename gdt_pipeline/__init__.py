"""gdt-pipeline: geometric digital twins of long-living assets from CAD and 3D scans, with uncertainty-aware change
detection. This module is the public API a plugin builds on: the hook marker, the stage record and the data types."""

from importlib.metadata import PackageNotFoundError, version

from .errors import GdtError, InputError, PluginError, StageError, WorkflowError
from .plugins import (
    BoxRead,
    BoxSource,
    ExecutorOptions,
    ExecutorSpec,
    ReaderSpec,
    ReadRequest,
    StageContext,
    StageSpec,
    TileExecutor,
    family_stage,
    hookimpl,
    hookspec,
)
from .types import (
    BoxUncertainty,
    Change,
    ChangeState,
    Composite,
    CompositeItem,
    Correspondences,
    Dataset,
    EpochInfo,
    FusionReason,
    GaussianUncertainty,
    ItemView,
    MixtureUncertainty,
    Region99,
    RegionOfView,
    Registration,
    ScannerGeometry,
    Scores,
    Segment,
    SensorPose,
    SourceInfo,
    Uncertainty,
)

try:
    __version__ = version("gdt-pipeline")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"

__all__ = [
    "BoxRead",
    "BoxSource",
    "BoxUncertainty",
    "Change",
    "ChangeState",
    "Composite",
    "CompositeItem",
    "Correspondences",
    "Dataset",
    "EpochInfo",
    "ExecutorOptions",
    "ExecutorSpec",
    "FusionReason",
    "GaussianUncertainty",
    "GdtError",
    "InputError",
    "ItemView",
    "MixtureUncertainty",
    "PluginError",
    "ReadRequest",
    "ReaderSpec",
    "Region99",
    "RegionOfView",
    "Registration",
    "ScannerGeometry",
    "Scores",
    "Segment",
    "SensorPose",
    "SourceInfo",
    "StageContext",
    "StageError",
    "StageSpec",
    "TileExecutor",
    "Uncertainty",
    "WorkflowError",
    "__version__",
    "family_stage",
    "hookimpl",
    "hookspec",
]
