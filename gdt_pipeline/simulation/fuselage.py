"""The paper's fuselage scene (Sec. 5.2): a fuselage side-wall section as CAD and a precise scan in which five
brackets were added and one removed.

Geometry (metres; fuselage axis along x, z up): a skin panel (radius 1.95 m, 1.6 m long, ±45° about +y, 3 mm
thick), three frames (web and inner flange) at a 0.53 m pitch, seven stringers; brackets are small L-shaped parts
riveted to the frame webs, where a cabin is attached. E0 is the CAD: skin, frames, stringers and two brackets.
E1 is a structured-light scan (Artec Eva class, sub-millimetre noise) from six stations 0.9 m inside the cabin looking
out at the skin, and (``sweep``, the default) 28 handheld stations within the frame bays looking at the four
bracket-carrying web faces from 0.5 m at 7 angles each: the way one scans brackets, which sit behind the frames'
inner flanges, so that their catalogue models can be fitted. One of the two CAD brackets was removed and five new
ones were fitted.
``part_bracket.obj`` is the bracket's catalogue model in its own frame (its solid centre at the origin), for the
fusion's part fitting.

Ground truth beside the scans: per point the object hit, its noise-free position and whether it is off the CAD
by more than ``TOLERANCE``; per CAD facet whether it was removed and whether a station could see it; per object
new/removed/unchanged, and each bracket's centre (the centroid of its solid).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..geometry import distance_to
from .objects import write_objects
from .paper_scene import TOLERANCE, EpochFiles
from .scanner import ScannerSpec, simulate_scan, write_scan
from .visibility import facets_in_view_of_stations

RADIUS = 1.95
LENGTH = 1.6
HALF_SPAN_DEG = 45.0
FRAMES_X = (0.27, 0.80, 1.33)
STRINGERS_DEG = (-36.0, -24.0, -12.0, 0.0, 12.0, 24.0, 36.0)
# (frame index, side of the web -1/+1, angle in degrees): where brackets sit on the frame webs
CAD_BRACKETS = {"bracket_kept": (1, +1, 6.0), "bracket_removed": (0, +1, -18.0)}
NEW_BRACKETS = {"bracket_new_1": (0, +1, 18.0), "bracket_new_2": (1, -1, -18.0), "bracket_new_3": (1, +1, -30.0),
                "bracket_new_4": (2, -1, 6.0), "bracket_new_5": (2, -1, 30.0)}


def _sector(r0: float, r1: float, a0: float, a1: float, x0: float, x1: float, segments: int):  # -> trimesh.Trimesh
    """A watertight annular-sector block in cylindrical coordinates about the x axis (angles in radians from +y)."""
    import trimesh

    ang = np.linspace(a0, a1, segments + 1)
    ring = []
    for x in (x0, x1):
        for r in (r0, r1):
            ring.append(np.column_stack([np.full_like(ang, x), r * np.cos(ang), r * np.sin(ang)]))
    verts = np.vstack(ring)  # 4 rings: (x0,r0) (x0,r1) (x1,r0) (x1,r1), each segments+1 long
    n = segments + 1
    faces, outward = [], []
    mid = (ang[:-1] + ang[1:]) / 2
    radial = np.column_stack([np.zeros_like(mid), np.cos(mid), np.sin(mid)])
    ex = np.array([1.0, 0.0, 0.0])
    # inner (r0 rings 0,2), outer (r1 rings 1,3), near end (x0 rings 0,1), far end (x1 rings 2,3), each with the
    # direction its faces must point out of the block
    for p, s, out in ((0, 2, -radial), (1, 3, radial), (0, 1, -ex + 0 * radial), (2, 3, ex + 0 * radial)):
        for i in range(segments):
            faces += [[p * n + i, s * n + i, s * n + i + 1], [p * n + i, s * n + i + 1, p * n + i]]
            faces[-1] = [p * n + i, s * n + i + 1, p * n + i + 1]
            outward += [out[i], out[i]]
    for i, sign in ((0, -1.0), (segments, 1.0)):  # the two radial caps
        tangent = sign * np.array([0.0, -np.sin(ang[i]), np.cos(ang[i])])
        faces += [[0 * n + i, 1 * n + i, 3 * n + i], [0 * n + i, 3 * n + i, 2 * n + i]]
        outward += [tangent, tangent]
    faces = np.array(faces)
    v = verts[faces]
    normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flip = np.einsum("ij,ij->i", normal, np.array(outward)) < 0
    faces[flip] = faces[flip][:, ::-1]
    mesh = trimesh.Trimesh(verts, faces, process=True)
    return mesh


def _box(centre: np.ndarray, axes: np.ndarray, extents: tuple[float, float, float]):  # -> trimesh.Trimesh
    """A box with the given centre, orthonormal axes (rows) and extents."""
    import trimesh

    t = np.eye(4)
    t[:3, :3] = axes.T
    t[:3, 3] = centre
    return trimesh.creation.box(extents=extents, transform=t)


def _bracket(frame: int, side: int, angle_deg: float):  # -> trimesh.Trimesh
    """An L-shaped bracket on a frame web: a plate against the web and a leg standing off it towards the cabin."""
    import trimesh

    a = np.radians(angle_deg)
    radial = np.array([0.0, np.cos(a), np.sin(a)])
    tangent = np.array([0.0, -np.sin(a), np.cos(a)])
    axis = np.array([1.0, 0.0, 0.0])
    web_face = FRAMES_X[frame] + side * 0.01
    plate = _box(np.array([web_face + side * 0.0025, 0, 0]) + radial * (RADIUS - 0.055),
                 np.vstack([axis, tangent, radial]), (0.005, 0.06, 0.05))
    leg = _box(np.array([web_face + side * 0.025, 0, 0]) + radial * (RADIUS - 0.0775),
               np.vstack([axis, tangent, radial]), (0.04, 0.06, 0.005))
    return trimesh.util.concatenate([plate, leg])


def fuselage_objects() -> dict[str, tuple[object, str]]:
    """The fuselage section's parts: name -> (mesh, 'cad' | 'new')."""
    import trimesh

    half = np.radians(HALF_SPAN_DEG)
    objects: dict[str, tuple[object, str]] = {
        "skin": (_sector(RADIUS, RADIUS + 0.003, -half, half, 0.0, LENGTH, 90), "cad")}
    frames = []
    for x in FRAMES_X:
        frames.append(_sector(RADIUS - 0.09, RADIUS, -half, half, x - 0.01, x + 0.01, 90))  # web
        frames.append(_sector(RADIUS - 0.095, RADIUS - 0.09, -half, half, x - 0.03, x + 0.03, 90))  # inner flange
    objects["frames"] = (trimesh.util.concatenate(frames), "cad")
    stringers = []
    for deg in STRINGERS_DEG:
        a, w = np.radians(deg), 0.012 / RADIUS
        stringers.append(_sector(RADIUS - 0.025, RADIUS, a - w, a + w, 0.0, LENGTH, 1))
    objects["stringers"] = (trimesh.util.concatenate(stringers), "cad")
    for name, where in CAD_BRACKETS.items():
        objects[name] = (_bracket(*where), "cad")
    for name, where in NEW_BRACKETS.items():
        objects[name] = (_bracket(*where), "new")
    return objects


def station(x: float, angle_deg: float, standoff: float) -> tuple[np.ndarray, np.ndarray]:
    """A scanner inside the cabin looking straight out at the skin: (eye, target)."""
    a = np.radians(angle_deg)
    radial = np.array([0.0, np.cos(a), np.sin(a)])
    return np.array([x, 0, 0]) + radial * (RADIUS - standoff), np.array([x, 0, 0]) + radial * RADIUS


def web_station(frame: int, side: int, angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A handheld station in the bay on ``side`` of a frame, 0.5 m along the axis from the web and 0.18 m inside the
    skin, looking back at the web face where brackets sit: (eye, target)."""
    a = np.radians(angle_deg)
    radial = np.array([0.0, np.cos(a), np.sin(a)])
    x = FRAMES_X[frame]
    return np.array([x + side * 0.5, 0, 0]) + radial * (RADIUS - 0.18), np.array([x, 0, 0]) + radial * (RADIUS - 0.06)


# the web faces that carry brackets: (frame index, side)
BRACKET_WEBS = ((0, +1), (1, -1), (1, +1), (2, -1))
WEB_ANGLES_DEG = (-36.0, -24.0, -12.0, 0.0, 12.0, 24.0, 36.0)


def bracket_part():  # -> trimesh.Trimesh
    """The bracket's catalogue model in its own frame: the solid's centre at the origin."""
    mesh = _bracket(0, +1, 0.0)
    mesh.apply_translation(-mesh.center_mass)
    return mesh


def make_fuselage_scene(out_dir: str | Path, *, seed: int = 0, points_per_m2: float = 30000.0,
                        web_points_per_m2: float = 40000.0, sweep: bool = True) -> dict[str, EpochFiles]:
    """Write the fuselage scene's CAD (E0) and its precise scan (E1) with ground truth into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    objects = fuselage_objects()
    cad_names = [n for n, (_, kind) in objects.items() if kind == "cad"]
    files: dict[str, EpochFiles] = {
        "E0": EpochFiles("E0", scans=write_objects(out, {n: (m, kind == "cad") for n, (m, kind) in objects.items()}))}
    present = [n for n in objects if n != "bracket_removed"]
    now = [objects[n][0] for n in present]
    before = [objects[n][0] for n in cad_names]
    spec = ScannerSpec(profile="structured_light", points_per_m2=points_per_m2, fov_deg=60.0, max_range=3.0)
    web_spec = spec.model_copy(update={"points_per_m2": web_points_per_m2})
    stations = [station(x, deg, 0.9) for x in (0.53, 1.07) for deg in (-28.0, 0.0, 28.0)]
    specs = [spec] * len(stations)
    if sweep:
        stations += [web_station(f, side, deg) for f, side in BRACKET_WEBS for deg in WEB_ANGLES_DEG]
        specs += [web_spec] * (len(stations) - len(specs))
    (out / "part_bracket.obj").write_text(bracket_part().export(file_type="obj", include_normals=False,
                                                                include_texture=False))
    ef = EpochFiles("E1")
    changed_all = []
    for k, ((eye, target), st_spec) in enumerate(zip(stations, specs, strict=True)):
        scan = simulate_scan(now, eye, target, st_spec, rng)
        changed = distance_to(before, scan.clean) > TOLERANCE
        changed_all.append(changed)
        written = write_scan(scan, out / f"scan_E1_s{k}.ply", object_names=present, changed=changed,
                             spec=st_spec)
        ef.scans.append(written["scan"])
        ef.viewpoints.append(eye.tolist())
    states = {n: ("removed" if n == "bracket_removed" else "new" if objects[n][1] == "new" else "unchanged")
              for n in objects}
    centres = {n: objects[n][0].center_mass.tolist() for n in objects if n.startswith("bracket")}
    truth: dict[str, np.ndarray] = {"changed": np.concatenate(changed_all), "objects": np.array(json.dumps(states)),
                                    "centres": np.array(json.dumps(centres))}
    eyes = np.array([s[0] for s in stations])
    for n in cad_names:
        mesh = objects[n][0]
        truth[f"in_view__{n}"] = facets_in_view_of_stations(mesh, stations, now, spec)  # frusta: same fov for all
        truth[f"removed__{n}"] = np.full(len(mesh.faces), n == "bracket_removed")
    path = out / "truth_E1.npz"
    with open(path, "wb") as fh:
        np.savez(fh, **truth)
    files["E1"] = EpochFiles("E1", ef.scans, ef.viewpoints, path)
    summary = {"scene": "fuselage", "seed": seed, "tolerance": TOLERANCE, "epochs": {"E1": {
        "stations": len(eyes), "points": int(truth["changed"].size), "changed": int(truth["changed"].sum()),
        "objects": states, "bracket_centres": centres, "profile": spec.profile}}}
    (out / "scene.json").write_text(json.dumps(summary, indent=2) + "\n")
    return files

