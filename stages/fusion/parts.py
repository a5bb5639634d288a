"""Fitting catalogue parts (CAD models of brackets, fittings, ...) to the segments an epoch found new.

A segment's centroid is the centroid of what the sensors measured: a part scanned from one side has its hidden faces
missing, so that centroid sits off the part's own centre by up to half its depth. Where the user gives the part's
model, it is registered to the segment (multi-start point-to-plane ICP, Open3D) and the segment records the part, its
pose, the fitted model's centre and the fit's RMS, which is the paper's "geometric center of the bracket".
"""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from gdt_pipeline.geometry import raycasting_scene


@dataclass(frozen=True)
class PartModel:
    """A catalogue part ready to fit: its surface samples with normals and its centre, in the part's frame."""

    name: str
    path: Path
    sha256: str
    samples: np.ndarray
    normals: np.ndarray
    centre: np.ndarray
    diagonal: float
    max_rms: float
    vertices: np.ndarray
    faces: np.ndarray

    @functools.cached_property
    def _scene(self):  # -> o3d.t.geometry.RaycastingScene, built once per part for all its fits
        return raycasting_scene([(self.vertices, self.faces)])

    def distance(self, to_part: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Each point's distance to the part's surface, after ``to_part`` (4x4) takes it into the part's frame."""
        import open3d as o3d

        local = points @ to_part[:3, :3].T + to_part[:3, 3]
        return self._scene.compute_distance(o3d.core.Tensor(local.astype(np.float32))).numpy().astype(np.float64)


@dataclass(frozen=True)
class PartFit:
    """The best fit of a part to a segment: pose (4x4, part frame to twin), fitted centre, RMS and the share of the
    segment's elements within ``max_rms`` of the fitted model."""

    part: str
    pose: np.ndarray
    centre: np.ndarray
    rms: float
    fitness: float
    accepted: bool
    ambiguous: bool


def load_part(name: str, path: Path, max_rms: float | None, seed: int, samples: int = 20000) -> PartModel:
    """Read a part's mesh (any format trimesh reads) and sample its surface."""
    import trimesh

    try:
        # unprocessed: merging the vertices of shells that touch (a bracket's plate and leg) makes their shared
        # edges non-manifold, and the solid's centre would fall back to the area centroid
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ValueError(f"part {name!r}: cannot read its model {path}: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"part {name!r}: {path} holds no triangles")
    return mesh_model(name, path, hashlib.sha256(path.read_bytes()).hexdigest(), mesh, max_rms, seed, samples)


def mesh_model(name: str, path: Path, sha256: str, mesh, max_rms: float | None, seed: int, samples: int
               ) -> PartModel:  # mesh: trimesh.Trimesh
    """A mesh as a part model: its surface sampled, its centre and diagonal, the RMS a fit may reach (default 2 % of
    the diagonal)."""
    import trimesh

    pts, face = trimesh.sample.sample_surface(mesh, samples, seed=seed)
    # a closed part's centre is its solid's; an open surface has only its area centroid
    centre = np.asarray(mesh.center_mass if mesh.is_watertight else mesh.centroid, dtype=np.float64)
    diagonal = float(np.linalg.norm(mesh.extents))
    return PartModel(name=name, path=path, sha256=sha256, samples=np.asarray(pts, dtype=np.float64),
                     normals=np.asarray(mesh.face_normals[face]), centre=centre, diagonal=diagonal,
                     max_rms=float(max_rms) if max_rms is not None else 0.02 * diagonal,
                     vertices=np.asarray(mesh.vertices, dtype=np.float64), faces=np.asarray(mesh.faces, dtype=np.int64))


def _starts(seg: np.ndarray, part: PartModel) -> list[np.ndarray]:
    """Initial rotations (part frame to twin): the 24 axis-aligned ones, and the same composed with the rotation
    that takes the part's principal axes onto the segment's (a partial view's axes are only roughly the part's)."""
    def axes(p: np.ndarray) -> np.ndarray:
        _, v = np.linalg.eigh(np.cov((p - p.mean(axis=0)).T))
        v = v[:, ::-1]
        if np.linalg.det(v) < 0:
            v[:, 2] *= -1
        return v

    group = Rotation.create_group("O").as_matrix()
    align = axes(seg) @ axes(part.samples).T
    return [g for g in group] + [align @ g for g in group]


def fit_part(points: np.ndarray, part: PartModel, rng: np.random.Generator, max_points: int = 2000) -> PartFit:
    """Register ``part`` to a segment's element positions and score the fit on all of them."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    src_pts = points if len(points) <= max_points else points[rng.choice(len(points), max_points, replace=False)]
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src_pts))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(part.samples))
    target.normals = o3d.utility.Vector3dVector(part.normals)
    est = reg.TransformationEstimationPointToPlane()
    crit = reg.ICPConvergenceCriteria(max_iteration=40)
    centroid = src_pts.mean(axis=0)
    tried: list[tuple[float, np.ndarray]] = []
    # ICP moves the segment onto the part; the part's pose in the twin is the inverse. Each start is scored by the
    # RMS of the exact point-to-surface distance of the points it used
    for rot in _starts(src_pts, part):
        init = np.eye(4)
        init[:3, :3] = rot.T
        init[:3, 3] = part.samples.mean(axis=0) - rot.T @ centroid
        t = init
        for reach in (0.25, 0.08, 0.02):
            t = reg.registration_icp(source, target, reach * part.diagonal, t, est, crit).transformation
        t = np.asarray(t)
        tried.append((float(np.sqrt(np.mean(part.distance(t, src_pts) ** 2))), t))
    best = min(tried, key=lambda st: st[0])
    pose = np.linalg.inv(best[1])
    centre = pose[:3, :3] @ part.centre + pose[:3, 3]
    # a view that shows too little of the part (one face of a bracket) fits it in several places equally well:
    # then the centre is not known, and the fit says so instead of picking one
    ambiguous = False
    for score, t in tried:
        if score <= 1.5 * best[0]:
            other = np.linalg.inv(t)
            if np.linalg.norm(other[:3, :3] @ part.centre + other[:3, 3] - centre) > 0.05 * part.diagonal:
                ambiguous = True
                break
    # the fit is scored on every element, not only the ones ICP used
    d = part.distance(best[1], points)
    rms = float(np.sqrt(np.mean(d**2)))
    fitness = float(np.mean(d <= part.max_rms))
    return PartFit(part=part.name, pose=pose, centre=centre, rms=rms, fitness=fitness,
                   accepted=rms <= part.max_rms and fitness >= 0.9 and not ambiguous, ambiguous=ambiguous)
