"""Scanner simulator: ray casting with real occlusion (Open3D RaycastingScene), per-point anisotropic and
heterogeneous noise from a sensor profile (range noise growing with range and incidence, smaller lateral noise),
optional registration error per scan, output as point clouds (or reconstructed meshes) with the sensor pose and the
per-point ground truth beside each scan.

The noise model is the one the ``sensor_model`` uncertainty stage assumes (``gdt_pipeline.sensors``), so a workflow
can state exactly the simulator's model; presets: ``tof_low_cost`` (Lenovo Phab 2 Pro class, centimetres) and
``structured_light`` (Artec Eva class, sub-millimetre).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat
from scipy.spatial.transform import Rotation

from ..geometry import beam_frames, raycasting_scene
from ..sensors import PRESETS, SensorProfile


class ScannerSpec(BaseModel):
    """How a simulated scanner sees: geometry of its rays, density, range and noise."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["pinhole", "spherical"] = "pinhole"
    fov_deg: float = Field(60.0, gt=0, le=360, description="Horizontal field of view (pinhole); azimuth span "
                                                           "(spherical).")
    aspect: PositiveFloat = Field(4 / 3, description="Width / height of the pinhole image; spherical: azimuth span "
                                                     "/ elevation span.")
    points_per_m2: PositiveFloat = Field(20000.0, description="Ray density at the target distance.")
    max_range: PositiveFloat = Field(10.0, description="Hits farther away are dropped (m).")
    profile: str = Field("tof_low_cost", description="Noise: a preset or a sensor profile file.")
    registration_sigma_deg: float = Field(0.0, ge=0, description="Per-scan random rotation error (deg, per axis).")
    registration_sigma_m: float = Field(0.0, ge=0, description="Per-scan random translation error (m, per axis).")


@dataclass(frozen=True)
class SimulatedScan:
    """One simulated scan: noisy points and everything known about them."""

    points: np.ndarray
    clean: np.ndarray
    object_id: np.ndarray
    facet_id: np.ndarray
    viewpoint: np.ndarray
    sigma_range: np.ndarray
    sigma_lateral: np.ndarray
    registration_error: np.ndarray  # 4x4 applied to the noisy points (identity when none)
    target: np.ndarray | None = None  # where the scanner looked (with the viewpoint and the spec: its frustum)
    pixel: np.ndarray | None = None  # per point, its ray's index in the scanner's image (row-major over ``grid``)
    grid: tuple[int, int] | None = None  # the image's rows and columns


def _rays(spec: ScannerSpec, eye: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    import open3d as o3d

    dist = float(np.linalg.norm(target - eye))
    step = np.sqrt(1.0 / spec.points_per_m2) / dist  # angular pitch giving the density at the target
    if spec.kind == "pinhole":
        width = int(np.ceil(np.radians(spec.fov_deg) / step))
        height = max(1, int(np.ceil(width / spec.aspect)))
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            fov_deg=spec.fov_deg, center=target.tolist(), eye=eye.tolist(), up=[0.0, 0.0, 1.0], width_px=width,
            height_px=height)
        grid = rays.shape[0], rays.shape[1]
        return rays.numpy().reshape(-1, 6).astype(np.float64), grid
    fwd = (target - eye) / dist
    az0 = np.arctan2(fwd[1], fwd[0])
    el0 = np.arcsin(np.clip(fwd[2], -1, 1))
    span_az = np.radians(spec.fov_deg)
    span_el = span_az / spec.aspect
    az = az0 + np.arange(-span_az / 2, span_az / 2, step)
    el = el0 + np.arange(-span_el / 2, span_el / 2, step)
    a, e = np.meshgrid(az, el, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)
    return np.hstack([np.broadcast_to(eye, d.shape), d]), (len(az), len(el))


def simulate_scan(meshes: list, eye: np.ndarray, target: np.ndarray, spec: ScannerSpec, rng: np.random.Generator,
                  profile: SensorProfile | None = None) -> SimulatedScan:
    """Cast the scanner's rays at the scene (a list of trimesh meshes) and return the noisy hits with their truth."""
    import open3d as o3d

    profile = profile or PRESETS[spec.profile]
    eye, target = np.asarray(eye, dtype=np.float64), np.asarray(target, dtype=np.float64)
    scene = raycasting_scene(meshes)
    rays, grid = _rays(spec, eye, target)
    ans = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    length = np.linalg.norm(rays[:, 3:], axis=1)
    dist = ans["t_hit"].numpy().astype(np.float64) * length
    hit = np.isfinite(dist) & (dist <= spec.max_range)
    d = rays[hit, 3:] / length[hit, None]
    clean = rays[hit, :3] + d * dist[hit, None]
    normals = ans["primitive_normals"].numpy()[hit].astype(np.float64)
    cos = np.abs(np.einsum("ij,ij->i", normals, d))
    s_r, s_l = profile.sigmas(dist[hit], cos, "m")
    u, v = beam_frames(d)
    z = rng.standard_normal((len(clean), 3))
    noisy = clean + d * (z[:, :1] * s_r[:, None]) + (u * z[:, 1:2] + v * z[:, 2:3]) * s_l[:, None]
    err = np.eye(4)
    if spec.registration_sigma_deg > 0 or spec.registration_sigma_m > 0:
        err[:3, :3] = Rotation.from_rotvec(np.radians(rng.normal(0, spec.registration_sigma_deg, 3))).as_matrix()
        centre = clean.mean(axis=0) if len(clean) else np.zeros(3)
        err[:3, 3] = centre - err[:3, :3] @ centre + rng.normal(0, spec.registration_sigma_m, 3)
        noisy = noisy @ err[:3, :3].T + err[:3, 3]
    return SimulatedScan(points=noisy, clean=clean, object_id=ans["geometry_ids"].numpy()[hit].astype(np.int64),
                         facet_id=ans["primitive_ids"].numpy()[hit].astype(np.int64), viewpoint=eye,
                         sigma_range=s_r, sigma_lateral=s_l, registration_error=err, target=target,
                         pixel=np.flatnonzero(hit), grid=grid)


def write_scan(scan: SimulatedScan, path: Path, *, object_names: list[str], changed: np.ndarray | None = None,
               spec: ScannerSpec | None = None, as_mesh: bool = False, poisson_depth: int = 8,
               poisson_threads: int = -1, mesher: str = "poisson") -> dict[str, Path]:
    """Write a scan (PLY points, or a mesh: Poisson-reconstructed at octree depth ``poisson_depth``, or with
    ``mesher="grid"`` the scanner's own range image triangulated), its pose and sensor as JSON, and its truth (npz).
    ``poisson_threads=1`` makes the Poisson mesh reproducible (threads sum in any order)."""
    import open3d as o3d

    path.parent.mkdir(parents=True, exist_ok=True)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan.points))
    if as_mesh and mesher == "grid":
        from .range_mesh import range_image_mesh

        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(scan.points),
                                         o3d.utility.Vector3iVector(range_image_mesh(scan)))
        mesh.remove_unreferenced_vertices()
        o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=False)
    elif as_mesh:
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=20))
        pcd.orient_normals_towards_camera_location(scan.viewpoint)
        mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=poisson_depth, n_threads=poisson_threads)
        dens = np.asarray(density)
        mesh.remove_vertices_by_mask(dens < np.quantile(dens, 0.05))  # trim the surface Poisson invents
        o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=False)
    else:
        o3d.io.write_point_cloud(str(path), pcd, write_ascii=False)
    truth = path.with_name(path.stem + "_truth.npz")
    with open(truth, "wb") as fh:
        np.savez(fh, clean=scan.clean, object_id=scan.object_id, facet_id=scan.facet_id,
                 object_names=np.array(object_names), changed=np.zeros(len(scan.clean), bool) if changed is None
                 else changed, sigma_range=scan.sigma_range, sigma_lateral=scan.sigma_lateral,
                 registration_error=scan.registration_error)
    pose = path.with_name(path.stem + "_pose.json")
    pose.write_text(json.dumps({"viewpoint": scan.viewpoint.tolist(), "points": len(scan.points),
                                "target": None if scan.target is None else scan.target.tolist(), "up": [0.0, 0.0, 1.0],
                                "registration_error": scan.registration_error.tolist(),
                                "scanner": None if spec is None else spec.model_dump()}, indent=2) + "\n")
    return {"scan": path, "truth": truth, "pose": pose}
