"""Synthetic scenes with ground truth: a first version of the paper's test scene (Sec. 5.1), used by the demo.

E0 is the as-designed CAD (a small cuboid and two identical frustums, one OBJ per object). E1 is a simulated
time-of-flight scan of the as-is scene, in which a larger cuboid has appeared: rays are cast from a few viewpoints
with Open3D's RaycastingScene (so occlusion is real), and every hit gets anisotropic Gaussian noise, larger along the
beam than across it. Beside the scan go the per-point ground truth (noise-free position, object hit, changed or
not, viewpoint) and a scene.json describing it all. The same seed writes byte-identical files.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .simulate import raycasting_scene


@dataclass(frozen=True)
class SceneFiles:
    """What a scene generator wrote."""

    root: Path
    cad: list[Path]
    scans: dict[str, Path]
    truth: dict[str, Path]
    viewpoints: dict[str, list[list[float]]] = field(default_factory=dict)


def _frustum(base: float, top: float, height: float):  # -> trimesh.Trimesh
    """A square frustum standing on z=0, as the convex hull of its eight corners (watertight, triangulated)."""
    import trimesh

    b, t = base / 2, top / 2
    corners = np.array([[-b, -b, 0], [b, -b, 0], [b, b, 0], [-b, b, 0],
                        [-t, -t, height], [t, -t, height], [t, t, height], [-t, t, height]], dtype=np.float64)
    return trimesh.convex.convex_hull(corners)


def _cuboid(extents: tuple[float, float, float]):  # -> trimesh.Trimesh
    """A box standing on z=0."""
    import trimesh

    box = trimesh.creation.box(extents=extents)
    box.apply_translation((0, 0, extents[2] / 2))
    return box


def scene_objects() -> dict[str, tuple[object, bool]]:
    """The objects of the test scene, in metres: name -> (mesh, present in the CAD of E0)."""
    objects = {
        "small_cuboid": (_cuboid((0.30, 0.20, 0.15)), (-0.45, -0.40), True),
        "frustum_a": (_frustum(0.30, 0.15, 0.25), (0.45, -0.40), True),
        "frustum_b": (_frustum(0.30, 0.15, 0.25), (0.45, 0.45), True),
        "large_cuboid": (_cuboid((0.50, 0.35, 0.30)), (-0.40, 0.45), False),
    }
    out = {}
    for name, (mesh, (x, y), in_cad) in objects.items():
        mesh.apply_translation((x, y, 0.0))
        out[name] = (mesh, in_cad)
    return out


def _beam_frames(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to each unit beam direction (vectorised Gram-Schmidt)."""
    helper = np.where(np.abs(d[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    u = np.cross(d, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(d, u)


def simulate_tof_scan(meshes: list, viewpoints: np.ndarray, target: np.ndarray, *, rng: np.random.Generator,
                      points_per_m2: float, noise_sigma: float, fov_deg: float = 60.0, aspect: float = 4 / 3
                      ) -> dict[str, np.ndarray]:
    """Cast a pinhole camera's rays from each viewpoint at ``target`` and return noisy hits with their truth."""
    import open3d as o3d

    scene = raycasting_scene(meshes)
    clean, obj, view, dirs = [], [], [], []
    for k, eye in enumerate(viewpoints):
        rng_dist = float(np.linalg.norm(target - eye))
        step = np.sqrt(1.0 / points_per_m2) / rng_dist  # angular pixel pitch giving that density at the target
        width = int(np.ceil(np.radians(fov_deg) / step))
        height = int(np.ceil(width / aspect))
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            fov_deg=fov_deg, center=target.tolist(), eye=eye.tolist(), up=[0.0, 0.0, 1.0],
            width_px=width, height_px=height)
        ans = scene.cast_rays(rays)
        r = rays.numpy().reshape(-1, 6).astype(np.float64)
        t = ans["t_hit"].numpy().reshape(-1)
        hit = np.isfinite(t)
        d = r[hit, 3:] / np.linalg.norm(r[hit, 3:], axis=1, keepdims=True)
        origin = r[hit, :3]
        # recompute the hit in float64 from the float32 distance along the unit direction
        dist = t[hit] * np.linalg.norm(r[hit, 3:], axis=1)
        clean.append(origin + d * dist[:, None])
        obj.append(ans["geometry_ids"].numpy().reshape(-1)[hit].astype(np.int64))
        view.append(np.full(int(hit.sum()), k, dtype=np.int64))
        dirs.append(d)
    clean_a, obj_a, view_a, d_a = (np.concatenate(x) for x in (clean, obj, view, dirs))
    u, v = _beam_frames(d_a)
    z = rng.standard_normal((len(clean_a), 3))
    noisy = clean_a + d_a * (z[:, :1] * noise_sigma) + u * (z[:, 1:2] * noise_sigma / 3) \
        + v * (z[:, 2:3] * noise_sigma / 3)
    return {"points": noisy, "clean": clean_a, "object_id": obj_a, "viewpoint": view_a, "beam": d_a}


def write_objects(root: Path, objects: dict[str, tuple[object, bool]]) -> list[Path]:
    """Write each object as ``cad_<name>.obj`` (in the CAD) or ``truth_<name>.obj`` (only in reality); the CAD paths."""
    cad = []
    for name, (mesh, in_cad) in objects.items():
        path = root / (f"cad_{name}.obj" if in_cad else f"truth_{name}.obj")
        path.write_text(mesh.export(file_type="obj", include_normals=False, include_texture=False))
        if in_cad:
            cad.append(path)
    return cad


def make_test_scene(out_dir: str | Path, *, seed: int = 0, points_per_m2: float = 20000.0,
                    noise_sigma: float = 0.004) -> SceneFiles:
    """Write the demo test scene (CAD of E0 and a simulated noisy scan of E1) with ground truth into out_dir."""
    import open3d as o3d

    root = Path(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    objects = scene_objects()
    names = list(objects)
    cad_paths = write_objects(root, objects)
    target = np.array([0.0, 0.0, 0.15])
    az = np.radians([-60.0, 30.0, 150.0])
    viewpoints = np.column_stack([2.0 * np.cos(az), 2.0 * np.sin(az), np.full(3, 1.2)])
    rng = np.random.default_rng(seed)
    scan = simulate_tof_scan([objects[n][0] for n in names], viewpoints, target, rng=rng,
                             points_per_m2=points_per_m2, noise_sigma=noise_sigma)
    in_cad = np.array([objects[n][1] for n in names])
    changed = ~in_cad[scan["object_id"]]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan["points"]))
    scan_path = root / "scan_E1.ply"
    o3d.io.write_point_cloud(str(scan_path), pcd, write_ascii=False)
    truth_path = root / "truth_E1.npz"
    with open(truth_path, "wb") as fh:
        np.savez(fh, clean=scan["clean"], object_id=scan["object_id"], object_names=np.array(names),
                 changed=changed, viewpoint=scan["viewpoint"])
    meta = {"scene": "test-scene", "seed": seed, "units": "m", "noise_sigma_along_beam": noise_sigma,
            "noise_sigma_lateral": noise_sigma / 3, "points_per_m2": points_per_m2,
            "objects": {n: {"in_cad_E0": bool(objects[n][1]), "in_E1": True} for n in names},
            "viewpoints": {"E1": viewpoints.tolist()}, "target": target.tolist(),
            "counts": {"E1": {"points": len(changed), "changed": int(changed.sum())}}}
    (root / "scene.json").write_text(json.dumps(meta, indent=2) + "\n")
    return SceneFiles(root=root, cad=cad_paths, scans={"E1": scan_path}, truth={"E1": truth_path},
                      viewpoints={"E1": viewpoints.tolist()})
