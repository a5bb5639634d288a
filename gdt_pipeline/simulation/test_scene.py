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

from ..sensors import SensorProfile
from .objects import scene_objects, write_objects
from .scanner import ScannerSpec, simulate_scan


@dataclass(frozen=True)
class SceneFiles:
    """What a scene generator wrote."""

    root: Path
    cad: list[Path]
    scans: dict[str, Path]
    truth: dict[str, Path]
    viewpoints: dict[str, list[list[float]]] = field(default_factory=dict)


def constant_noise_profile(noise_sigma: float) -> SensorProfile:
    """The demo's noise as a sensor profile: ``noise_sigma`` along the beam, a third of it across, at any range."""
    # no range terms and a cos floor of 1 make the profile's σ exactly these constants (a0 + 0·r + 0·r² = a0, / 1.0)
    return SensorProfile(name="constant_noise", units="m", range_sigma=[noise_sigma, 0.0, 0.0],
                         lateral_sigma=[noise_sigma / 3, 0.0], min_cos_incidence=1.0)


def simulate_stations(meshes: list, viewpoints: np.ndarray, target: np.ndarray, *, rng: np.random.Generator,
                      points_per_m2: float, noise_sigma: float, fov_deg: float = 60.0, aspect: float = 4 / 3
                      ) -> dict[str, np.ndarray]:
    """A pinhole scan from each viewpoint at ``target`` with constant noise, concatenated: noisy hits and their truth
    (``viewpoint`` holds the index of the station each point came from)."""
    # an infinite range keeps every hit, as the demo always has
    spec = ScannerSpec(kind="pinhole", fov_deg=fov_deg, aspect=aspect, points_per_m2=points_per_m2,
                       max_range=float("inf"))
    profile = constant_noise_profile(noise_sigma)
    scans = [simulate_scan(meshes, eye, target, spec, rng, profile=profile) for eye in viewpoints]
    return {"points": np.concatenate([s.points for s in scans]), "clean": np.concatenate([s.clean for s in scans]),
            "object_id": np.concatenate([s.object_id for s in scans]),
            "viewpoint": np.concatenate([np.full(len(s.clean), k, dtype=np.int64) for k, s in enumerate(scans)])}


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
    scan = simulate_stations([objects[n][0] for n in names], viewpoints, target, rng=rng,
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
