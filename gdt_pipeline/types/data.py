"""Datasets and what stages make of them: region of view, correspondences, scores, change, registration."""
from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .arrays import frozen_array
from .pose import SensorPose
from .states import Kind, Role
from .triangles import triangle_normals
from .uncertainty import Uncertainty


@dataclass(frozen=True)
class SourceInfo:
    """Where a dataset came from: file, its sha256, the units it was written in and the scale applied on reading."""

    path: str
    sha256: str
    units: str = "m"
    scale: float = 1.0
    reader: str = ""
    # what reading did to the data (a reader's ``ReadRequest.report``), e.g. degenerate facets dropped
    notes: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)


@dataclass(frozen=True)
class Dataset:
    """One geometry of one epoch: a point set ``points (N,3)`` or a triangle mesh ``points (V,3)`` + ``faces (F,3)``.

    ``pose`` is the station that measured it (one source for every stage: pose file, file header or workflow, in
    that order; ``viewpoints`` then holds its position). ``fields`` are per-element values a reader found (E57 or
    LAS ``intensity`` (E,), ``color`` (E,3) in 0..1); ``meta`` what identifies the dataset outside the twin (a part's
    name, an IFC GlobalId and class, an E57 scan's guid), written on its prim.
    """

    name: str
    role: Role
    points: np.ndarray
    faces: np.ndarray | None = None
    source: SourceInfo | None = None
    uncertainty: Uncertainty | None = None
    viewpoints: np.ndarray | None = None
    pose: SensorPose | None = None
    fields: dict[str, np.ndarray] = field(default_factory=dict, compare=False, hash=False)
    meta: dict[str, str] = field(default_factory=dict, compare=False, hash=False)

    def __post_init__(self) -> None:
        pts = frozen_array(self.points, np.float64, (None, 3), f"dataset {self.name!r} points")
        object.__setattr__(self, "points", pts)
        if self.faces is not None:
            faces = frozen_array(self.faces, np.int64, (None, 3), f"dataset {self.name!r} faces")
            if faces.size and (faces.min() < 0 or faces.max() >= len(pts)):
                raise ValueError(f"dataset {self.name!r}: face indices outside 0..{len(pts) - 1}")
            object.__setattr__(self, "faces", faces)
        if self.viewpoints is not None:
            vps = frozen_array(self.viewpoints, np.float64, (None, 3), f"dataset {self.name!r} viewpoints")
            object.__setattr__(self, "viewpoints", vps)
        n = self.n_elements
        for key, values in self.fields.items():
            if len(values) != n:
                raise ValueError(f"dataset {self.name!r}: field {key!r} has {len(values)} rows for {n} elements")

    def take_fields(self, elements: np.ndarray) -> dict[str, np.ndarray]:
        """The per-element fields at ``elements`` (for a subset of the dataset)."""
        return {key: values[elements] for key, values in self.fields.items()}

    @property
    def kind(self) -> Kind:
        """"mesh" when the dataset has faces, else "points"."""
        return "mesh" if self.faces is not None else "points"

    @property
    def n_elements(self) -> int:
        """Number of elements: facets of a mesh, points of a point set."""
        return len(self.faces) if self.faces is not None else len(self.points)

    def element_positions(self) -> np.ndarray:
        """One position per element: the point itself, or the facet's centroid."""
        if self.faces is None:
            return self.points
        return np.asarray(self.points[self.faces].mean(axis=1))

    def facet_normals(self, idx: np.ndarray | None = None, unit: bool = False) -> np.ndarray:
        """Normals of the facets (all, or those at ``idx``) by the right-hand rule: twice the facet's area long, or
        of unit length with ``unit``."""
        if self.faces is None:
            raise ValueError(f"dataset {self.name!r} is a point set: it has no facets")
        normal = triangle_normals(self.points[self.faces if idx is None else self.faces[idx]])
        if unit:
            normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        return normal

    def facet_areas(self, idx: np.ndarray | None = None) -> np.ndarray:
        """Areas of the facets (all, or those at ``idx``)."""
        return np.asarray(0.5 * np.linalg.norm(self.facet_normals(idx), axis=1))

    def element_covariance(self) -> np.ndarray:
        """Per-element covariance ``(E,3,3)`` of the attached uncertainty (second moments of a box)."""
        if self.uncertainty is None:
            raise ValueError(f"dataset {self.name!r} has no uncertainty attached (add an uncertainty stage)")
        return self.uncertainty.covariance(self.n_elements)

    def with_uncertainty(self, uncertainty: Uncertainty) -> Dataset:
        """A copy with ``uncertainty`` attached, checked against the element count."""
        uncertainty.covariance(self.n_elements)  # raises on a row-count mismatch
        return dataclasses.replace(self, uncertainty=uncertainty)

    def transformed(self, transform: np.ndarray) -> Dataset:
        """A copy moved by a 4x4 rigid transform; covariances and box axes are rotated with it."""
        t = np.asarray(transform, dtype=np.float64)
        rot, trans = t[:3, :3], t[:3, 3]
        unc = None if self.uncertainty is None else self.uncertainty.rotated(rot)
        vps = None if self.viewpoints is None else self.viewpoints @ rot.T + trans
        pose = None if self.pose is None else self.pose.transformed(rot, trans)
        return dataclasses.replace(self, points=self.points @ rot.T + trans, uncertainty=unc, viewpoints=vps,
                                   pose=pose)


@dataclass(frozen=True)
class ItemView:
    """What a region-of-view stage found of one reference item, per element: in view (inside the volume and seen,
    not occluded), matched (the recent data confirms it present) and, where the stage judged elements by their
    area, the share of each element's area a station saw (present or seen through) and saw through (removed)."""

    in_view: np.ndarray
    matched: np.ndarray
    seen_fraction: np.ndarray | None = None
    removed_fraction: np.ndarray | None = None

    def take(self, elements: np.ndarray) -> ItemView:
        """The view of the elements ``elements``."""
        def sub(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[elements]

        return ItemView(self.in_view[elements], self.matched[elements], sub(self.seen_fraction),
                        sub(self.removed_fraction))


@dataclass(frozen=True)
class RegionOfView:
    """The space the sensors of an epoch measured: closed triangle surfaces (their union; ``parts`` gives the facet
    count of each closed part, default one part) with a vectorised ``contains``; and, once a region-of-view stage
    has looked at the reference, per reference item (by key) what it found of its elements (``views``)."""

    vertices: np.ndarray
    faces: np.ndarray
    parts: tuple[int, ...] = ()
    views: dict[str, ItemView] = field(default_factory=dict)
    method: str = ""

    def __post_init__(self) -> None:
        verts = frozen_array(self.vertices, np.float64, (None, 3), "region of view vertices")
        object.__setattr__(self, "vertices", verts)
        object.__setattr__(self, "faces", frozen_array(self.faces, np.int64, (None, 3), "region of view faces"))
        parts = tuple(int(p) for p in self.parts) or (len(self.faces),)
        if sum(parts) != len(self.faces):
            raise ValueError(f"region of view: parts {parts} do not add up to its {len(self.faces)} facets")
        object.__setattr__(self, "parts", parts)

    @classmethod
    def box(cls, lower: np.ndarray | list[float], upper: np.ndarray | list[float]) -> RegionOfView:
        """An axis-aligned box region from its two corners."""
        import trimesh

        lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
        if np.any(hi <= lo):
            raise ValueError(f"region of view box: upper {hi.tolist()} must exceed lower {lo.tolist()}")
        mesh = trimesh.creation.box(extents=hi - lo)
        mesh.apply_translation((hi + lo) / 2)
        return cls(mesh.vertices, mesh.faces)

    def contains(self, points: np.ndarray, part: int | None = None) -> np.ndarray:
        """Boolean mask of the points strictly inside any of the closed parts, or inside part ``part`` only (parity
        of ray intersections each)."""
        import open3d as o3d  # imported here: open3d is heavy and only a region-of-view query needs it

        tensor = o3d.core.Tensor.from_numpy  # the arrays below are fresh copies: sharing them is safe
        pts = tensor(np.array(points, dtype=np.float32).reshape(-1, 3))
        inside = np.zeros(pts.shape[0], dtype=bool)
        start = 0
        # one scene per part: overlapping closed parts would cancel each other's parity
        for k, n in enumerate(self.parts):
            if part is not None and k != part:
                start += n
                continue
            scene = o3d.t.geometry.RaycastingScene()
            faces = self.faces[start:start + n]
            used, local = np.unique(faces, return_inverse=True)
            scene.add_triangles(tensor(self.vertices[used].astype(np.float32)),
                                tensor(local.reshape(-1, 3).astype(np.uint32)))
            inside |= scene.compute_occupancy(pts).numpy().astype(bool)
            start += n
        return inside


@dataclass(frozen=True)
class Scores:
    """Dissimilarity per element of one recent dataset (NaN where there was no correspondence)."""

    query: int
    score: np.ndarray
    measure: str
    p_value: np.ndarray | None = None
    tolerance: float | None = None  # ε_T of a numerical integration, when the measure used one
    match: np.ndarray | None = None  # per element, the index of the winning correspondence candidate (-1: none)
    # per element, whether the reference has data at its place (its sampling, or a mesh surface over it); an element
    # without a correspondence is new only where it does, else not comparable. None: covered everywhere
    covered: np.ndarray | None = None
    # simulate(rng, n): scores of n unchanged pairs drawn from this dataset's actual pairs' uncertainty models (the
    # null distribution a calibrated threshold needs); None when the measure cannot simulate.
    simulate: Callable[[np.random.Generator, int], np.ndarray] | None = field(default=None, compare=False,
                                                                               repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "score", frozen_array(self.score, np.float64, (None,), "score"))
        if self.p_value is not None:
            object.__setattr__(self, "p_value", frozen_array(self.p_value, np.float64, (len(self.score),), "p-value"))
        if self.covered is not None:
            object.__setattr__(self, "covered", frozen_array(self.covered, np.bool_, (len(self.score),), "covered"))


@dataclass(frozen=True)
class Change:
    """Per element of one recent dataset: the score, the change mask and the change state."""

    query: int
    score: np.ndarray
    mask: np.ndarray
    state: np.ndarray
    p_value: np.ndarray | None = None
    threshold: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "score", frozen_array(self.score, np.float64, (None,), "change score"))
        n = len(self.score)
        object.__setattr__(self, "mask", frozen_array(self.mask, np.bool_, (n,), "change mask"))
        object.__setattr__(self, "state", frozen_array(self.state, np.uint8, (n,), "change state"))
        if self.p_value is not None:
            object.__setattr__(self, "p_value", frozen_array(self.p_value, np.float64, (n,), "change p-value"))


@dataclass(frozen=True)
class Registration:
    """A rigid transform from the recent data to the twin, with its quality and 6x6 covariance when known.

    The covariance is over small rotations ω about ``center`` and translations: a point x moves by ω × (x − center)
    + t. Expressing it about a centre near the data keeps georeferenced coordinates well conditioned.
    """

    transform: np.ndarray
    fitness: float = 1.0
    rmse: float = 0.0
    covariance: np.ndarray | None = None  # 6x6 over (ωx, ωy, ωz, tx, ty, tz), rotation about ``center``
    method: str = ""
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "transform", frozen_array(self.transform, np.float64, (4, 4), "transform"))
        object.__setattr__(self, "center", frozen_array(self.center, np.float64, (3,), "covariance center"))
        if self.covariance is not None:
            object.__setattr__(self, "covariance", frozen_array(self.covariance, np.float64, (6, 6), "covariance"))
