"""The speed benchmark's scene (issue 20): a real CAD part with a block added on top, scanned with structured light
from four stations 0.6 m away, and the default chain's workflow for it.

The part is ``../shared/data/cad_meshes/counter.unitsmm.STL`` (83,750 facets, mm, scaled to metres) with ±0.5 mm
tolerance boxes; without the shared data a generated part of at least 80 k facets stands in (a finely triangulated,
gently waved plate of the same size, so that its facets are as small and as many). The block is 5 × 5 × 3 cm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from gdt_pipeline.simulation.scanner import ScannerSpec, simulate_scan, write_scan

COUNTER = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "cad_meshes" / "counter.unitsmm.STL"
STATION_DISTANCE = 0.6
TOLERANCE = 0.0005

WORKFLOW = """\
name: speed-bench-{n}
description: the counter part (CAD, ±0.5 mm) and {n} structured-light points from four stations; a block added.
twin: twin
seed: 7
units: m
epochs:
  - id: E0
    role: as-designed
    inputs:
      - {{path: cad_part.stl}}
  - id: E1
    role: as-is
    inputs:
{scans}
stages:
  - uses: constant
    role: as-designed
    with: {{model: box, half_widths: [{tol}, {tol}, {tol}]}}
  - uses: sensor_model
    role: as-is
    with: {{profile: structured_light}}
  - uses: sensor_frustum
    role: as-is
  - uses: auto
    role: as-is
  - uses: bhattacharyya
    role: as-is
  - uses: calibrated_threshold
    role: as-is
  - uses: most_reliable
"""


def cad_part(counter: Path = COUNTER) -> tuple[trimesh.Trimesh, str]:
    """The CAD part in metres, centred on the origin and standing on z = 0, and where it came from."""
    if counter.exists():
        part = trimesh.load(counter, force="mesh")
        part.apply_scale(0.001)
        source = f"{counter.name} (shared data)"
    else:
        part = _generated_part()
        source = "generated plate (shared data absent)"
    lo, hi = part.bounds
    part.apply_translation((-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]))
    return part, source


def _generated_part(n: int = 205) -> trimesh.Trimesh:
    """A 0.3 × 0.3 × 0.026 m plate like the counter: a top of 2 (n − 1)² small facets (83,232 at n = 205) with a
    gentle 2 mm wave (not flat, so that normals and correspondences meet varied geometry), walls of one facet
    pair per top edge, a bottom fanned from its centre; watertight, 85,680 facets."""
    x = np.linspace(-0.15, 0.15, n)
    gx, gy = np.meshgrid(x, x, indexing="ij")
    top = np.column_stack([gx.ravel(), gy.ravel(), 0.026 + 0.002 * np.sin(gx.ravel() * 40) * np.cos(gy.ravel() * 30)])
    grid = np.arange(n * n).reshape(n, n)
    quads = np.stack([grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]], axis=-1).reshape(-1, 4)
    faces = [quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]
    ring = np.concatenate([grid[:-1, 0], grid[-1, :-1], grid[:0:-1, -1], grid[0, :0:-1]])  # the top's rim, in order
    bottom = top[ring] * np.array([1.0, 1.0, 0.0])
    low = n * n + np.arange(len(ring))
    centre = n * n + len(ring)
    nxt = np.roll(np.arange(len(ring)), -1)
    faces += [np.column_stack([ring, low, low[nxt]]), np.column_stack([ring, low[nxt], ring[nxt]]),
              np.column_stack([low[nxt], low, np.full(len(ring), centre)])]
    mesh = trimesh.Trimesh(np.vstack([top, bottom, [[0.0, 0.0, 0.0]]]), np.vstack(faces), process=False)
    mesh.fix_normals()
    return mesh


def block_on(part: trimesh.Trimesh) -> trimesh.Trimesh:
    """The 5 × 5 × 3 cm block standing on the part's top, off centre."""
    block = trimesh.creation.box(extents=(0.05, 0.05, 0.03))
    block.apply_translation((0.06, -0.04, part.bounds[1][2] + 0.015))
    return block


def stations() -> np.ndarray:
    """Four stations 0.6 m from the part's centre, 45° up, one per quadrant."""
    az = np.radians([45.0, 135.0, 225.0, 315.0])
    el = np.radians(45.0)
    return STATION_DISTANCE * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                        np.full(4, np.sin(el))], axis=1)


def build(folder: Path, n_points: int, seed: int = 0, counter: Path = COUNTER) -> dict:
    """Write the scene for about ``n_points`` scan points into ``folder``: CAD, scans with pose and truth files,
    ``workflow.yaml``; return what was written (paths, point count, source of the part)."""
    folder.mkdir(parents=True, exist_ok=True)
    part, source = cad_part(counter)
    part.export(folder / "cad_part.stl")
    asis = [part, block_on(part)]
    rng = np.random.default_rng(seed)
    target = np.array([0.0, 0.0, part.bounds[1][2] / 2])
    eyes = stations()
    spec = ScannerSpec(fov_deg=40.0, points_per_m2=1000.0, max_range=5.0, profile="structured_light")
    for _ in range(3):  # the image's size is rounded to whole pixels: refine the density a few times
        probe = sum(len(simulate_scan(asis, e, target, spec, rng).points) for e in eyes)
        spec = spec.model_copy(update={"points_per_m2": spec.points_per_m2 * n_points / max(probe, 1)})
    scans, total = [], 0
    for k, eye in enumerate(eyes):
        scan = simulate_scan(asis, eye, target, spec, rng)
        path = folder / f"scan_s{k}.ply"
        write_scan(scan, path, object_names=["part", "block"], changed=scan.object_id == 1, spec=spec)
        scans.append(f"      - {{path: {path.name}, viewpoints: [[{eye[0]:.6f}, {eye[1]:.6f}, {eye[2]:.6f}]]}}")
        total += len(scan.points)
    workflow = folder / "workflow.yaml"
    workflow.write_text(WORKFLOW.format(n=total, scans="\n".join(scans), tol=TOLERANCE))
    return {"workflow": workflow, "scans": [folder / f"scan_s{k}.ply" for k in range(len(eyes))],
            "cad": folder / "cad_part.stl", "points": total, "facets": len(part.faces), "source": source}
