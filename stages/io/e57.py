"""E57 (ASTM E2807), the exchange format of terrestrial and handheld scanners, through pye57 (libE57Format).

Every scan of a file becomes one dataset, read scan by scan, in the file's frame (the scan's pose applied), with
intensity and colour carried when the scan has them, and the scan's station (its pose: translation and rotation,
from the scan's own frame to the file's) as the dataset's pose, so that ``sensor_model`` and ``sensor_frustum``
need no ``viewpoints:``. E57 coordinates are metres by the standard.

libE57Format checks every page's CRC, so a truncated or corrupted file is an error, never points; the points read are
checked against the scan's declared count. (Declared ``cartesianBounds`` are not checked: the standard puts them in
the scan's own frame, but common writers, pye57's among them, store them moved by the pose.)
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gdt_pipeline import Dataset, InputError, ReaderSpec, ReadRequest, SensorPose

from .version import VERSION


class E57Params(BaseModel):
    """Parameters of the pye57 E57 reader."""

    model_config = ConfigDict(extra="forbid")
    scans: list[int] | None = Field(None, description="Read only these scans (0-based, in the file's order); "
                                                      "default every scan.")


def _scan_pose(header: Any, k: int, name: str) -> SensorPose | None:
    """The station of scan ``k``: its pose's translation and rotation (scan frame to file frame), when it has one."""
    if not header.has_pose():
        return None
    rotation = np.asarray(header.rotation_matrix, dtype=np.float64)
    translation = np.asarray(header.translation, dtype=np.float64)
    if not (np.all(np.isfinite(rotation)) and np.all(np.isfinite(translation))):
        raise InputError(f"scan {k} ({name!r}): its pose holds values that are not finite")
    return SensorPose(position=translation, source="file_header", origin=f"E57 scan {k} {name!r}", rotation=rotation)


def _text(header: Any, key: str) -> str:
    try:
        return str(header[key].value())
    except Exception:  # pye57 raises its C++ library's exception for an absent child; absent is just empty
        return ""


def _colour(data: dict[str, np.ndarray], header: Any) -> np.ndarray | None:
    """The scan's colours as 0..1 (E57 states each channel's limits; 0..255 when it does not)."""
    if not all(f"color{c}" in data for c in ("Red", "Green", "Blue")):
        return None
    channels = []
    for c in ("Red", "Green", "Blue"):
        try:
            lo = float(header["colorLimits"][f"color{c}Minimum"].value())
            hi = float(header["colorLimits"][f"color{c}Maximum"].value())
        except Exception:  # limits are optional in E57
            lo, hi = 0.0, 255.0
        channels.append((np.asarray(data[f"color{c}"], dtype=np.float64) - lo) / max(hi - lo, 1e-12))
    return np.clip(np.column_stack(channels), 0.0, 1.0).astype(np.float32)


def _read_scan(e57: Any, k: int, req: ReadRequest) -> Dataset:
    """Scan ``k`` as one dataset in the file's frame, with its station, intensity and colour."""
    header = e57.get_header(k)
    name = _text(header, "name") or f"scan{k}"
    declared = int(header.point_count)
    data = e57.read_scan(k, intensity=True, colors=True, transform=True, ignore_missing_fields=True)
    points = np.column_stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]]).astype(np.float64)
    if len(points) > declared:
        raise InputError(f"scan {k} ({name!r}): {len(points)} points read but the scan declares {declared}")
    if len(points) == 0:
        raise InputError(f"scan {k} ({name!r}): no valid points (it declares {declared})")
    fields: dict[str, np.ndarray] = {}
    if "intensity" in data:
        fields["intensity"] = np.asarray(data["intensity"], dtype=np.float32)
    colour = _colour(data, header)
    if colour is not None:
        fields["color"] = colour
    meta = {"e57_scan": str(k), **({"guid": guid} if (guid := _text(header, "guid")) else {})}
    return Dataset(name=name, role=req.role, points=points, pose=_scan_pose(header, k, name), fields=fields,
                   meta=meta)


def _checked_scan(e57: Any, k: int, req: ReadRequest) -> Dataset:
    """Scan ``k``, with libE57Format's refusal (a page whose CRC fails, a truncated binary section) named as such."""
    try:
        return _read_scan(e57, k, req)
    except InputError:
        raise
    except Exception as exc:  # libE57Format's own exception type, raised for damaged data
        raise InputError(f"scan {k}: the file is damaged: {str(exc).strip().splitlines()[0]}") from exc


def read_e57(req: ReadRequest) -> list[Dataset]:
    """Every scan of an E57 file (or those ``scans`` asks for) as one dataset each, with its station."""
    try:
        import pye57
    except ImportError as exc:
        raise InputError("reading E57 needs pye57: pip install pye57") from exc
    try:
        e57 = pye57.E57(str(req.path))
    except Exception as exc:  # libE57Format's own exception type: a file it cannot open is bad input
        raise InputError(f"not a readable E57 file: {exc}") from exc
    try:
        count = e57.scan_count
        wanted = list(range(count)) if req.params.scans is None else req.params.scans
        bad = [k for k in wanted if not 0 <= k < count]
        if bad:
            raise InputError(f"scans {bad} asked for, but the file holds {count} (0..{count - 1})")
        if not wanted:
            raise InputError("the file holds no scans (data3D is empty)")
        parts = [_checked_scan(e57, k, req) for k in wanted]
    finally:
        e57.close()
    req.report(units="m", scans=len(parts), points=[len(p.points) for p in parts],
               poses=sum(p.pose is not None for p in parts))
    return parts





READER = ReaderSpec(name="pye57_scans", version=VERSION, params=E57Params, read=read_e57, extensions=(".e57",),
                    description="E57 scans through pye57: one dataset per scan, its station from the header, "
                                "intensity and colour.")
