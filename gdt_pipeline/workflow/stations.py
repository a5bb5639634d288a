"""Before a run: a region-of-view stage whose sight test needs sensor positions gets them from every input of the
epochs it runs in (the workflow's ``viewpoints``, a pose file beside the scan, or an E57 header), or the workflow
does not validate."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import ValidationError

from ..plugins import Registry
from .marks import Problems


def _needs_stations(spec: Any, params: dict | None) -> str | None:
    """Why the stage needs sensor positions from the inputs (None: it does not)."""
    from ..region_of_view import SightParams

    if spec.family != "rov" or not (isinstance(spec.params, type) and issubclass(spec.params, SightParams)):
        return None
    try:
        p = spec.params.model_validate(params or {})
    except ValidationError:
        return None  # the params' own problems are reported elsewhere
    if p.viewpoints:
        return None
    if p.sight in ("depth", "stations"):
        return f"sight: {p.sight}"
    return "occlusion" if p.occlusion else None


def _has_station(inp: Any, base: Path) -> bool:
    """Whether an input names its sensor position: workflow viewpoints, a pose file beside it, an E57 file."""
    from ..runner.poses import pose_file_for

    path = base / inp.path
    if not path.is_file():
        return True  # a missing input is reported as such
    return bool(inp.viewpoints) or path.suffix.lower() == ".e57" or pose_file_for(path).is_file()


def station_problems(model: Any, registry: Registry, problems: Problems, base: Path,
                     held: frozenset[str] = frozenset()) -> None:
    """Each region-of-view entry that needs stations, checked against the inputs of the epochs it runs in (not
    those in ``held``: a twin holds them, they will not run)."""
    for s_index, entry in enumerate(model.stages):
        spec = registry.get(entry.uses)
        why = _needs_stations(spec, entry.with_)
        if why is None:
            continue
        for epoch in (e for e in model.epochs if e.id not in held):
            missing = [inp.path for inp in epoch.inputs if not _has_station(inp, base)]
            if entry.applies_to(epoch) and missing:
                problems.add(("stages", s_index, "uses"),
                             f"stage {spec.name!r} needs sensor positions ({why}), but in epoch {epoch.id!r} "
                             f"{', '.join(missing)} carries none (no `viewpoints:` on the input, no pose file "
                             f"<scan>_pose.json beside it, not E57): state them, give the stage `viewpoints`, or "
                             f"use `uses: coverage` for data without stations (airborne, voxelised)")
                break
