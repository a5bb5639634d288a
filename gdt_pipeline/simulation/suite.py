"""A suite of random plant- and cabin-like scenes with truth by area, for ``gdt eval --suite``.

Each scene: a floor plate with 6–14 parts (cabinets, lying pipes, standing cylinders, plates, panels, L-brackets,
U-channel rails) in a random non-overlapping layout, its CAD (E0, one OBJ per part), and a simulated scan (E1) of
the as-is scene in which 1–3 parts were added, 1–2 removed and 1–2 moved, from 1–4 pinhole stations. The suites:

- ``tof``: a low-cost ToF camera (``tof_low_cost`` × 0.3–1.0, from about the pipe-rack report's 1 mm + 2.5 mm·r²
  to the preset's 2 mm + 8 mm·r² along the beam) 1.5–4.5 m from the scene, point scans;
- ``precise``: a structured-light scanner (``structured_light`` × 0.5–2) 0.5–1.5 m away, point scans;
- ``precise-mesh``: the same, each scan written as a mesh the way a scanner's software makes one: its range image
  triangulated, not across depth jumps (``range_mesh``).

Beside the scans: the true sensor profile (``sensor.yaml``), per-scan truth (``_truth.npz``; per facet with its
area for mesh scans), ``truth_E1.npz`` (per CAD facet: area, visible and removed fractions; per part its state and
a moved part's displacement), ``workflow.yaml`` (the default chain) and ``scene.json`` (every draw). The same seed
writes byte-identical files."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..sensors import PRESETS, SensorProfile, save_profile
from .objects import write_objects
from .paper_scene import TOLERANCE
from .scanner import ScannerSpec, simulate_scan, write_scan
from .suite_layout import Layout, draw_layout
from .suite_truth import cad_facet_truth, clean_mesh_scan, mesh_facet_truth, point_changed
from .suite_workflow import write_workflow


@dataclass(frozen=True)
class SuiteSpec:
    """What a suite draws from: the sensor preset and its scale range, the station distances, the scan kind."""

    preset: str
    noise_scale: tuple[float, float]
    distance: tuple[float, float]
    as_mesh: bool


SUITES: dict[str, SuiteSpec] = {
    "tof": SuiteSpec("tof_low_cost", (0.3, 1.0), (1.5, 4.5), False),
    "precise": SuiteSpec("structured_light", (0.5, 2.0), (0.5, 1.5), False),
    "precise-mesh": SuiteSpec("structured_light", (0.5, 2.0), (0.5, 1.5), True),
}
POINT_BUDGET = (100_000, 200_000)  # total points of a scene (all stations), drawn uniformly
PILOT_DENSITY = 1000.0  # points/m² of the ray-count pilot that sets each station's density
PROFILE_FILE = "sensor.yaml"


@dataclass(frozen=True)
class SuiteScene:
    """What ``make_suite_scene`` wrote."""

    suite: str
    seed: int
    root: Path
    workflow: Path
    cad: list[Path]
    scans: list[Path]
    truth: Path
    viewpoints: list[list[float]]
    states: dict[str, str]
    points: int
    pose_files: bool
    as_mesh: bool


def scaled_profile(preset: str, scale: float) -> SensorProfile:
    """A preset with every σ coefficient scaled: the true noise of a scene's scanner."""
    base = PRESETS[preset]
    return base.model_copy(update={
        "name": f"{preset}_x{scale:.3f}", "range_sigma": [c * scale for c in base.range_sigma],
        "lateral_sigma": [c * scale for c in base.lateral_sigma],
        "description": f"{base.description} σ scaled by {scale:.3f} (a suite scene's true noise)."})


def draw_stations(rng: np.random.Generator, suite_spec: SuiteSpec, R: float, L: float
                  ) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """1–4 stations around the scene: (eye, target, horizontal fov in degrees), looking at it with some jitter."""
    n = int(rng.integers(1, 5))
    centre = np.array([0.0, 0.0, 0.1 * L])
    phi0 = rng.uniform(0, 2 * np.pi)
    out = []
    for i in range(n):
        phi = phi0 + 2 * np.pi * i / n + rng.uniform(-0.35, 0.35)
        elev = np.radians(rng.uniform(25.0, 60.0))
        dist = float(np.clip(R * rng.uniform(0.8, 1.25), *suite_spec.distance))
        eye = centre + dist * np.array([np.cos(elev) * np.cos(phi), np.cos(elev) * np.sin(phi), np.sin(elev)])
        target = centre + rng.normal(0.0, 0.06 * L, 3)
        out.append((eye, target, float(rng.uniform(50.0, 70.0))))
    return out


def station_specs(stations: list, meshes: list, L: float, budget: float) -> list[ScannerSpec]:
    """Each station's scanner, its density set so that the stations share ``budget`` points (a coarse pilot scan
    counts each one's hits per unit of density)."""
    specs = []
    for eye, target, fov in stations:
        spec = ScannerSpec(kind="pinhole", fov_deg=round(fov, 3), points_per_m2=PILOT_DENSITY,
                           max_range=round(float(np.linalg.norm(eye)) + 1.5 * L, 3), profile=PROFILE_FILE)
        pilot = simulate_scan(meshes, eye, target, spec, np.random.default_rng(0), profile=PRESETS["tof_low_cost"])
        density = PILOT_DENSITY * budget / len(stations) / max(len(pilot.points), 1)
        specs.append(spec.model_copy(update={"points_per_m2": round(float(density), 1)}))
    return specs


def _write_meshes(root: Path, layout: Layout) -> list[Path]:
    """The CAD (one OBJ per part, the floor first) and the true as-is places of new and moved parts
    (``truth_<name>.obj``)."""
    cad = write_objects(root, {"floor": (layout.floor, True), **{n: (p.mesh, True) for n, p in layout.cad.items()}})
    write_objects(root, {n: (layout.asis[n].mesh, False) for n, s in layout.states.items() if s in ("new", "moved")})
    return cad


def _scan_all(root: Path, layout: Layout, stations: list, specs: list[ScannerSpec], profile: SensorProfile,
              suite_spec: SuiteSpec, pose_files: bool, rng: np.random.Generator) -> tuple[list[Path], np.ndarray]:
    """Simulate and write every station's scan with its truth; the scan paths and all points' change truth."""
    names = ["floor", *layout.asis]
    asis = [layout.floor, *(p.mesh for p in layout.asis.values())]
    cad = [layout.floor, *(p.mesh for p in layout.cad.values())]
    paths, changed_all = [], []
    for k, ((eye, target, _), spec) in enumerate(zip(stations, specs, strict=True)):
        scan = simulate_scan(asis, eye, target, spec, rng, profile=profile)
        changed = point_changed(scan.clean, cad)
        changed_all.append(changed)
        written = write_scan(scan, root / f"scan_E1_s{k}.ply", object_names=names, changed=changed, spec=spec,
                             as_mesh=suite_spec.as_mesh, mesher="grid")
        if suite_spec.as_mesh:
            clean_mesh_scan(written["scan"], scan.points)  # drops the facets the reader would (no area)
            with np.load(written["truth"]) as t:
                arrays = {key: t[key] for key in t.files}
            arrays.update(mesh_facet_truth(written["scan"], asis, cad))
            with open(written["truth"], "wb") as fh:
                np.savez(fh, **arrays)
        if not pose_files:
            written["pose"].unlink()
        paths.append(written["scan"])
    return paths, np.concatenate(changed_all)


def _epoch_truth(path: Path, layout: Layout, stations: list, specs: list[ScannerSpec], changed: np.ndarray,
                 rng: np.random.Generator) -> None:
    """``truth_E1.npz``: per CAD facet its area, visible / vacated / visible-and-vacated fractions, removed and
    in-view flags; per part its state, a moved part's displacement and the as-is parts' solid centres."""
    asis = [layout.floor, *(p.mesh for p in layout.asis.values())]
    truth: dict[str, np.ndarray] = {"changed": changed, "objects": np.array(json.dumps(layout.states)),
                                    "displacements": np.array(json.dumps(layout.displacements)),
                                    "centres": np.array(json.dumps({n: p.mesh.center_mass.tolist()
                                                                    for n, p in layout.asis.items()})),
                                    "tolerance": np.array(TOLERANCE)}
    views = [(eye, target, spec) for (eye, target, _), spec in zip(stations, specs, strict=True)]
    for name, mesh in (("floor", layout.floor), *((n, p.mesh) for n, p in layout.cad.items())):
        for key, values in cad_facet_truth(mesh, layout.states[name], views, asis, rng).items():
            truth[f"{key}__{name}"] = values
    with open(path, "wb") as fh:
        np.savez(fh, **truth)


def make_suite_scene(suite: str, out_dir: str | Path, seed: int) -> SuiteScene:
    """Write one random scene of ``suite`` (see SUITES) with its truth and workflow into ``out_dir``."""
    if suite not in SUITES:
        raise ValueError(f"unknown scene suite {suite!r}; choose from {', '.join(SUITES)}")
    suite_spec = SUITES[suite]
    root = Path(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    scale = float(rng.uniform(*suite_spec.noise_scale))
    profile = scaled_profile(suite_spec.preset, scale)
    R = float(rng.uniform(*suite_spec.distance))
    L = R * float(rng.uniform(0.55, 0.8))
    pose_files = bool(rng.random() < 0.5)
    # a mesh scan has two facets per point: half the points keep its elements (and run time) at a point scan's
    budget = float(rng.uniform(*POINT_BUDGET)) / (2.0 if suite_spec.as_mesh else 1.0)
    # moves of 1–10 × the range σ at the scene's range, but not under the truth's own tolerance: a smaller move
    # changes no point or facet by the truth's rule
    move_scale = max(float(profile.sigmas(np.array([R]), None, "m")[0][0]), TOLERANCE)
    layout = draw_layout(rng, L, move_scale)
    stations = draw_stations(rng, suite_spec, R, L)
    asis = [layout.floor, *(p.mesh for p in layout.asis.values())]
    specs = station_specs(stations, asis, L, budget)
    cad = _write_meshes(root, layout)
    save_profile(profile, root / PROFILE_FILE)
    scans, changed = _scan_all(root, layout, stations, specs, profile, suite_spec, pose_files, rng)
    truth = root / "truth_E1.npz"
    _epoch_truth(truth, layout, stations, specs, changed, np.random.default_rng([seed, 1]))
    viewpoints = [[round(float(v), 6) for v in eye] for eye, _, _ in stations]
    workflow = write_workflow(root, suite, seed, cad, scans, viewpoints, PROFILE_FILE, suite_spec.as_mesh)
    summary = {"scene": f"suite-{suite}", "suite": suite, "seed": seed, "tolerance": TOLERANCE,
               "side_m": L, "range_m": R, "noise_scale": scale, "profile": profile.name, "pose_files": pose_files,
               "point_budget": budget, "move_scale_m": move_scale, "points": int(changed.size),
               "changed": int(changed.sum()), "objects": layout.states,
               "kinds": {n: p.kind for n, p in {**layout.cad, **layout.asis}.items()},
               "displacements": layout.displacements,
               "stations": [{"eye": eye.tolist(), "target": target.tolist(), "scanner": spec.model_dump()}
                            for (eye, target, _), spec in zip(stations, specs, strict=True)]}
    (root / "scene.json").write_text(json.dumps(summary, indent=2) + "\n")
    return SuiteScene(suite, seed, root, workflow, cad, scans, truth, viewpoints, dict(layout.states),
                       int(changed.size), pose_files, suite_spec.as_mesh)
