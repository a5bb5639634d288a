"""The ground truth a simulated scene leaves beside its scans: per point (``<scan>_truth.npz``) and per epoch
(``truth_<epoch>.npz``), and the true meshes of the objects present."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..names import identifier
from ..plugins import Registry
from ..runner import read_dataset
from ..types import ChangeState


class ScanTruth:
    """The per-point truth of an epoch's scans, concatenated in input order."""

    def __init__(self) -> None:
        self.changed: list[np.ndarray] = []
        self.points: list[np.ndarray] = []
        self.clean: list[np.ndarray] = []
        self.object: list[np.ndarray] = []
        self.scanpos: list[np.ndarray] = []
        self.keys: list[str] = []
        self.viewpoints: list[np.ndarray] = []
        self.profile: str | None = None

    def cat(self, name: str) -> np.ndarray:
        """One of the per-scan lists concatenated (empty when no scan has truth)."""
        return np.concatenate(getattr(self, name)) if getattr(self, name) else np.zeros(0)

    def add(self, station: int, key: str, truth: Any, points: np.ndarray, viewpoint: np.ndarray, pose: Path) -> None:
        """Append one scan: its truth file's arrays, its raw points, its station (0-based) and viewpoint."""
        names = [str(n) for n in truth["object_names"]]
        self.changed.append(truth["changed"].astype(bool))
        self.points.append(points)
        self.clean.append(truth["clean"])
        self.object.append(np.array(names, dtype=object)[truth["object_id"]])
        self.scanpos.append(np.full(len(points), station + 1, dtype=np.int32))
        self.keys.append(key)
        self.viewpoints.append(viewpoint)
        if pose.is_file():
            scanner = json.loads(pose.read_text()).get("scanner") or {}
            self.profile = scanner.get("profile", self.profile)


def read_scan_truth(wf: Any, epoch: Any, sets: dict, registry: Registry
                    ) -> tuple[ScanTruth, list[np.ndarray], list[str], Path | None]:
    """The truth of an epoch's scans beside the twin's change mask of the same points: (the truth, the twin's mask
    per scan, the inputs that could not be scored, the scene directory)."""
    truth = ScanTruth()
    pred, missing = [], []
    scene_dir = None
    for k, inp in enumerate(epoch.inputs):
        path = wf.input_path(inp)
        tpath = path.with_name(path.stem + "_truth.npz")
        if not tpath.is_file():
            missing.append(str(path))
            continue
        scene_dir = path.parent
        key = f"{epoch.id}_{inp.name or identifier(path.stem)}"
        t = np.load(tpath)
        es = sets[key]
        if es.n_elements != len(t["changed"]):
            missing.append(f"{path} (its elements are not its points: e.g. voxel Gaussians)")
            continue
        pred.append(es.state == ChangeState.NEW)
        raw = read_dataset(path, registry, name="peer", kind="points")
        pose = path.with_name(path.stem + "_pose.json")
        vp = inp.viewpoints[0] if inp.viewpoints else json.loads(pose.read_text())["viewpoint"]
        truth.add(k, key, t, raw.points, np.asarray(vp, dtype=np.float64), pose)
    return truth, pred, missing, scene_dir


def read_epoch_truth(scene_dir: Path | None, epoch_id: str) -> dict[str, Any] | None:
    """The epoch's truth file (per facet removed / in view, per object its state, bracket centres), or None."""
    if scene_dir is None or not (scene_dir / f"truth_{epoch_id}.npz").is_file():
        return None
    t = np.load(scene_dir / f"truth_{epoch_id}.npz")
    out: dict[str, Any] = {k: t[k] for k in t.files}
    out["objects"] = json.loads(str(t["objects"])) if "objects" in t.files else {}
    out["centres"] = json.loads(str(t["centres"])) if "centres" in t.files else {}
    return out


def truth_meshes(scene_dir: Path, states: dict[str, str]) -> dict[str, Any]:
    """The true meshes of the objects present in an epoch, from the scene's CAD and truth OBJ files."""
    import trimesh

    out = {}
    for name, state in states.items():
        if state in ("removed", "absent"):
            continue
        # the as-is place first: a suite scene's moved part has both its CAD place and where it stands now
        for stem in (f"truth_{name}", f"cad_{name}"):
            path = scene_dir / f"{stem}.obj"
            if path.is_file():
                out[name] = trimesh.load(path, force="mesh", process=False)
                break
    return out
