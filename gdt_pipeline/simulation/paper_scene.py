"""The paper's test scene (Sec. 5.1) over four epochs, with ground truth for every epoch.

E0: as-designed CAD of a small cuboid and two identical frustums (GUM tolerance boxes in the workflow).
E1: a noisy low-cost ToF scan (3 stations); the larger cuboid has been introduced.
E2: a precise structured-light scan (5 closer stations) of the same, unchanged scene; its region of view
    encloses E1's, so the better data should replace the worse.
E3: a partial scan (2 stations) in which two objects (the small cuboid and frustum A) were removed.

Ground truth per epoch (``truth_<epoch>.npz`` beside the scans): per scan point the object hit, its noise-free
position and whether it lies on geometry that was not in the previous epoch (off the previous as-is surfaces by
more than ``tolerance``); per object its state (new, removed, unchanged); and for E3 per facet of the previous
as-is objects whether it was removed and whether a station could see where it was.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry import distance_to
from .objects import scene_objects, write_objects
from .scanner import ScannerSpec, simulate_scan, write_scan
from .visibility import facets_in_view

TOLERANCE = 0.001  # m: a clean point farther than this from the previous as-is surfaces lies on changed geometry


@dataclass(frozen=True)
class EpochFiles:
    """What one simulated epoch wrote."""

    id: str
    scans: list[Path] = field(default_factory=list)
    viewpoints: list[list[float]] = field(default_factory=list)
    truth: Path | None = None


def _stations(n: int, radius: float, height: float, start_deg: float, span_deg: float) -> np.ndarray:
    az = np.radians(start_deg + np.linspace(0, span_deg, n, endpoint=n == 1 or span_deg < 360))
    return np.column_stack([radius * np.cos(az), radius * np.sin(az), np.full(n, height)])


def make_paper_test_scene(out_dir: str | Path, *, seed: int = 0) -> dict[str, EpochFiles]:
    """Write the four epochs of the paper's test scene with ground truth into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    objects = scene_objects()
    names = list(objects)
    target = np.array([0.0, 0.0, 0.15])
    files: dict[str, EpochFiles] = {}
    files["E0"] = EpochFiles("E0", scans=write_objects(out, objects))
    present = {
        "E0": [n for n in names if objects[n][1]],
        "E1": names,
        "E2": names,
        "E3": ["large_cuboid", "frustum_b"],
    }
    specs = {
        "E1": (ScannerSpec(profile="tof_low_cost", points_per_m2=15000), _stations(3, 2.0, 1.2, -60, 240)),
        "E2": (ScannerSpec(profile="structured_light", points_per_m2=20000, fov_deg=70),
               _stations(5, 2.2, 1.3, -80, 288)),
        # partial: two stations on the -y side, looking at where the small cuboid and frustum A stood
        "E3": (ScannerSpec(profile="structured_light", points_per_m2=20000, fov_deg=50), _stations(2, 1.6, 1.1,
                                                                                                   -120, 60)),
    }
    summary = {"seed": seed, "tolerance": TOLERANCE, "epochs": {}}
    for eid in ("E1", "E2", "E3"):
        spec, stations = specs[eid]
        prev = "E0" if eid == "E1" else f"E{int(eid[1]) - 1}"
        now = [objects[n][0] for n in present[eid]]
        before = [objects[n][0] for n in present[prev]]
        ef = EpochFiles(eid)
        all_changed = []
        for k, eye in enumerate(stations):
            scan = simulate_scan(now, eye, target, spec, rng)
            changed = distance_to(before, scan.clean) > TOLERANCE
            all_changed.append(changed)
            written = write_scan(scan, out / f"scan_{eid}_s{k}.ply", object_names=present[eid], changed=changed,
                                 spec=spec)
            ef.scans.append(written["scan"])
            ef.viewpoints.append(eye.tolist())
        states = {n: ("new" if n in present[eid] and n not in present[prev] else
                      "removed" if n in present[prev] and n not in present[eid] else
                      "unchanged" if n in present[eid] else "absent") for n in names}
        truth = {"objects": json.dumps(states)}
        if eid == "E3":
            for n in present[prev]:
                mesh = objects[n][0]
                truth[f"in_view__{n}"] = facets_in_view(mesh, stations, now, spec, target)
                truth[f"removed__{n}"] = np.full(len(mesh.faces), n not in present[eid])
        path = out / f"truth_{eid}.npz"
        with open(path, "wb") as fh:
            np.savez(fh, changed=np.concatenate(all_changed), **truth)
        ef = EpochFiles(eid, ef.scans, ef.viewpoints, path)
        files[eid] = ef
        summary["epochs"][eid] = {"stations": len(stations), "points": int(sum(len(c) for c in all_changed)),
                                  "changed": int(sum(int(c.sum()) for c in all_changed)), "objects": states,
                                  "profile": spec.profile}
    (out / "scene.json").write_text(json.dumps(summary, indent=2) + "\n")
    return files
