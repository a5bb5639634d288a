"""One source of station poses for every stage: the pose file beside a scan (``<scan>_pose.json``), else the scan
file's own header (E57), else the workflow's ``viewpoints:``. The source used is recorded in the input's provenance;
a lower source that disagrees with the one used is a warning there, never silently mixed in."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..types import Dataset, ScannerGeometry, SensorPose

log = logging.getLogger("gdt.poses")

POSE_FILE_SUFFIX = "_pose.json"
MAX_POSE_FILE_BYTES = 1 << 20


def pose_file_for(scan: Path) -> Path:
    """Where a scan's pose file would be: ``<scan stem>_pose.json`` beside it."""
    return scan.with_name(scan.stem + POSE_FILE_SUFFIX)


def _vector(data: dict[str, Any], key: str, path: Path) -> np.ndarray | None:
    value = data.get(key)
    if value is None:
        return None
    arr = np.asarray(value, dtype=np.float64) if isinstance(value, list) and len(value) == 3 else None
    if arr is None or not np.all(np.isfinite(arr)):
        raise InputError(f"{path}: {key!r} must be three finite numbers, not {value!r}")
    return arr


def read_pose_file(path: Path) -> SensorPose:
    """The station a pose file states: ``viewpoint`` (required), ``target``, ``rotation`` (3×3) and ``scanner``."""
    if path.stat().st_size > MAX_POSE_FILE_BYTES:
        raise InputError(f"{path}: a pose file of {path.stat().st_size} bytes is not a pose file (limit 1 MiB)")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not a readable pose file: {exc}") from exc
    if not isinstance(data, dict) or data.get("viewpoint") is None:
        raise InputError(f"{path}: a pose file needs a 'viewpoint': [x, y, z] (the station position)")
    rotation, scanner = data.get("rotation"), data.get("scanner")
    if scanner is not None and not isinstance(scanner, dict):
        raise InputError(f"{path}: 'scanner' must be a mapping (kind, fov_deg, aspect, max_range), not {scanner!r}")
    try:
        return SensorPose(position=_vector(data, "viewpoint", path), source="pose_file", origin=path.name,
                          rotation=None if rotation is None else np.asarray(rotation, dtype=np.float64),
                          target=_vector(data, "target", path),
                          scanner=None if scanner is None else ScannerGeometry.from_record(scanner))
    except (ValueError, TypeError) as exc:
        raise InputError(f"{path}: {exc}") from exc


def _workflow_poses(datasets: list[Dataset], viewpoints: list | None, where: str) -> list[np.ndarray | None]:
    """The workflow's viewpoints per dataset: all to a single dataset (several stations), else one each."""
    if viewpoints is None:
        return [None] * len(datasets)
    vps = np.asarray(viewpoints, dtype=np.float64).reshape(-1, 3)
    if len(datasets) == 1:
        return [vps]
    if len(vps) != len(datasets):
        raise InputError(f"{where}: the file holds {len(datasets)} datasets ({', '.join(d.name for d in datasets)}) "
                         f"but `viewpoints:` gives {len(vps)}: give one per dataset, in the file's order")
    return [vps[k:k + 1] for k in range(len(vps))]


def _disagreement(pose: SensorPose, given: np.ndarray | None) -> str | None:
    """What a lower-precedence source says that differs from the pose used (None when it agrees or is absent)."""
    if given is None:
        return None
    if len(given) == 1 and np.allclose(given[0], pose.position, rtol=0, atol=1e-6 * max(1.0, np.abs(given).max())):
        return None
    return (f"`viewpoints:` {np.round(given, 6).tolist()} differ from the {pose.source.replace('_', ' ')} "
            f"({pose.origin}) position {np.round(pose.position, 6).tolist()}; the {pose.source.replace('_', ' ')} "
            f"is used")


def resolve_poses(datasets: list[Dataset], scan: Path, viewpoints: list | None, scale: float, where: str
                  ) -> tuple[list[Dataset], list[dict[str, Any]]]:
    """The datasets of one input with their station (scaled to the twin's units) from the highest source there is,
    and per dataset the record of what was used (``{"source", "origin", "position", ...}`` or None, and warnings)."""
    pose_file = pose_file_for(scan)
    from_file = read_pose_file(pose_file) if pose_file.is_file() else None
    if from_file is not None and len(datasets) != 1:
        raise InputError(f"{where}: pose file {pose_file.name} states one station but the file holds "
                         f"{len(datasets)} datasets; give their poses in the file (E57) or `viewpoints:` instead")
    given = _workflow_poses(datasets, viewpoints, where)
    out, records = [], []
    for ds, vps in zip(datasets, given, strict=True):
        pose = from_file or ds.pose
        record: dict[str, Any] = {"pose": None}
        if pose is not None:
            pose = pose.scaled(scale)
            vps_scaled = None if vps is None else vps * scale
            warning = _disagreement(pose, vps_scaled)
            if warning:
                log.warning("%s: %s", where, warning)
                record["pose_warning"] = warning
            ds = dataclasses.replace(ds, pose=pose, viewpoints=pose.position[None])
        elif vps is not None:
            vps = vps * scale
            pose = SensorPose(vps[0], "workflow", "viewpoints:") if len(vps) == 1 else None
            ds = dataclasses.replace(ds, pose=pose, viewpoints=vps)
            record["viewpoints"] = vps.tolist()
        if pose is not None:
            record["pose"] = pose.record()
        out.append(ds)
        records.append(record)
    return out, records
