"""The data that flows between stages: plain, frozen, numpy-backed dataclasses.

Every per-element quantity is an array over elements (points of a point set, facets of a mesh), never a Python
object per element. Arrays handed to these classes are made read-only so that a stage cannot change what another
stage (or the twin) still holds; a stage builds new objects with :func:`dataclasses.replace` instead.

Element convention: for a point set an element is a point; for a triangle mesh an element is a facet, and a facet
is treated as infinitely many points that share the facet's uncertainty (paper Sec. 4.2.2).
"""

from twin_store import Segment

from .arrays import MappedRows, broadcast_rows, frozen_array
from .composite import Composite, CompositeItem, EpochInfo
from .correspondences import Correspondences
from .data import Change, Dataset, ItemView, RegionOfView, Registration, Scores, SourceInfo
from .pose import POSE_SOURCES, ScannerGeometry, SensorPose
from .region99 import BOX_99, CHI2_3_99, Region99
from .states import ChangeState, FusionReason, Kind, Role
from .uncertainty import BoxUncertainty, GaussianUncertainty, MixtureUncertainty, Uncertainty, concat_uncertainty

__all__ = [
    "BOX_99",
    "CHI2_3_99",
    "POSE_SOURCES",
    "BoxUncertainty",
    "Change",
    "ChangeState",
    "Composite",
    "CompositeItem",
    "Correspondences",
    "Dataset",
    "EpochInfo",
    "FusionReason",
    "GaussianUncertainty",
    "ItemView",
    "Kind",
    "MappedRows",
    "MixtureUncertainty",
    "Region99",
    "RegionOfView",
    "Registration",
    "Role",
    "ScannerGeometry",
    "Scores",
    "Segment",
    "SensorPose",
    "SourceInfo",
    "Uncertainty",
    "broadcast_rows",
    "concat_uncertainty",
    "frozen_array",
]
