"""``sensor_frustum``: the region of view is the union of the sensors' frusta, per recent dataset with viewpoints: a
pinhole frustum from the dataset's station when it states a target and a pinhole scanner (a pose file does), else the
tightest pinhole frustum around the directions to the dataset's own points (plus a margin)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from pydantic import Field, PositiveFloat

from gdt_pipeline import Dataset, RegionOfView, StageContext
from gdt_pipeline.memory import release_scratch_pages
from gdt_pipeline.region_of_view import SightParams, Station, Volume, rov_stage, view_frame


class FrustumParams(SightParams):
    """The union of the sensors' frusta."""

    fov_deg: float | None = Field(None, gt=0, lt=180, description="Horizontal field of view when no pose file says "
                                                                  "(default: fitted to the data).")
    aspect: PositiveFloat | None = Field(None, description="Width / height of the image when no pose file says.")
    near: float = Field(0.05, ge=0, description="Nearest range measured (twin units).")
    far: PositiveFloat | None = Field(None, description="Farthest range (default: the pose file's, else 1.05 × the "
                                                        "farthest point).")
    margin_deg: float = Field(1.0, ge=0, description="Angular margin around a frustum fitted to the data.")


def _frustum_mesh(eye: np.ndarray, fwd: np.ndarray, u: tuple[float, float], v: tuple[float, float], near: float,
                  far: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed pinhole frustum: image-plane tangent bounds u (right) and v (up), between near and far depth."""
    f, r, up = view_frame(fwd)
    corners = []
    for depth in (near, far):
        for a, b in ((u[0], v[0]), (u[1], v[0]), (u[1], v[1]), (u[0], v[1])):
            corners.append(eye + depth * (f + a * r + b * up))
    verts = np.array(corners)
    faces = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                      [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    return verts, faces


class Frustum(NamedTuple):
    """One sensor's frustum as a closed mesh, how it was found, the sensor position and its range when a pose file
    states it (nothing measured closer is empty space; 0 when unknown)."""

    vertices: np.ndarray
    faces: np.ndarray
    how: str
    eye: np.ndarray
    free_range: float = 0.0


def _dataset_frusta(ds: Dataset, p: FrustumParams) -> list[Frustum]:
    """A dataset's frusta: one from its station's pinhole scanner, else one per viewpoint fitted around the directions
    to its points."""
    pose = ds.pose
    pts = ds.element_positions()
    if pose is not None and pose.target is not None and pose.scanner is not None and pose.scanner.pinhole_frustum:
        eye, sc = pose.position, pose.scanner
        th = np.tan(np.radians(p.fov_deg or sc.fov_deg) / 2)
        tv = th / (p.aspect or sc.aspect)
        far = p.far or float(sc.max_range)
        verts, faces = _frustum_mesh(eye, pose.target - eye, (-th, th), (-tv, tv), p.near, far)
        # a scanner's empty rays are empty space; a reconstructed mesh's holes are where its surface was not kept
        free = far if ds.kind == "points" else 0.0
        return [Frustum(verts, faces, f"{ds.name}: pinhole frustum from its {pose.source.replace('_', ' ')} "
                                      f"({pose.origin})", eye, free)]
    if ds.viewpoints is None or not len(pts):
        return []
    out = []
    for eye in np.atleast_2d(ds.viewpoints):
        d = pts - eye
        fwd = d.mean(axis=0)
        f, r, up = view_frame(fwd)
        depth = d @ f
        if np.any(depth <= 1e-9 * np.linalg.norm(d, axis=1)):
            raise ValueError(f"dataset {ds.name!r}: its points surround viewpoint {eye.tolist()} (a spherical scan); "
                             f"state the region with manual_box")
        a, b = (d @ r) / depth, (d @ up) / depth
        m = np.tan(np.radians(p.margin_deg))
        far = p.far or 1.05 * float(np.linalg.norm(d, axis=1).max())
        verts, faces = _frustum_mesh(eye, f, (a.min() - m, a.max() + m), (b.min() - m, b.max() + m), p.near, far)
        out.append(Frustum(verts, faces, f"{ds.name}: frustum fitted to its points from {np.round(eye, 4).tolist()}",
                           eye))
    return out


def frustum_volume(ctx: StageContext) -> Volume:
    """The union of the sensors' frusta, each frustum its own station's volume."""
    frusta, owner = [], []
    for i, ds in enumerate(ctx["recent"]):
        found = _dataset_frusta(ds, ctx.params)
        release_scratch_pages()  # a fit reads every point: of a scan in a scratch file, its pages go after it
        frusta += found
        owner += [i] * len(found)
    if not frusta:
        raise ValueError("no recent dataset carries viewpoints or a pose file: give the inputs 'viewpoints' or use "
                         "manual_box")
    verts, faces, start = [], [], 0
    for fr in frusta:
        verts.append(fr.vertices)
        faces.append(fr.faces + start)
        start += len(fr.vertices)
    rov = RegionOfView(np.vstack(verts), np.vstack(faces), tuple(len(fr.faces) for fr in frusta))
    stations = [Station(fr.eye, lambda q, k=k: rov.contains(q, part=k), (i,), fr.free_range)
                for k, (fr, i) in enumerate(zip(frusta, owner, strict=True))]
    return Volume(rov, [fr.how for fr in frusta], stations)


SPEC = rov_stage(name="sensor_frustum", build=frustum_volume, params=FrustumParams, version="1.1.0",
                 description="Union of the sensors' frusta; in view where a station saw the element's place "
                             "(`sight`: depth images by default).")
