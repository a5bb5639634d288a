"""What the report tests share: a small twin with new geometry and segments, and reading the page's embedded data."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from gdt_pipeline.runner import run_workflow

from .conftest import make_cube_scene, write_cube_workflow

DATA = re.compile(r'<script type="application/json" id="gdt-data">(.*?)</script>', re.S)


def cube_twin(root: Path, registry: Any) -> Path:
    """The cube scene's twin: a CAD cube (E0), then a scan with a new box beside it (E1: new points, segments)."""
    scene = make_cube_scene(root / "scene")
    return run_workflow(write_cube_workflow(scene), registry=registry).twin


def page_data(html: str) -> dict[str, Any]:
    """The JSON the page's script draws (figures, segment boxes)."""
    found = DATA.search(html)
    assert found, "the page has no gdt-data script"
    return json.loads(found.group(1).replace("<\\/", "</"))


def decoded(value: Any) -> np.ndarray:
    """A plotly.js typed array (or a plain list) as numpy."""
    if isinstance(value, dict):
        return np.frombuffer(base64.b64decode(value["bdata"]), dtype=np.dtype(value["dtype"]).newbyteorder("<"))
    return np.asarray(value)


def view_points(html: str) -> dict[tuple[str, str], np.ndarray]:
    """The 3-D view's points per layer (state name, epoch), (N,3) float32."""
    out = {}
    for trace in page_data(html)["view"]["data"]:
        if trace["type"] == "scatter3d" and trace.get("meta"):
            xyz = np.column_stack([decoded(trace[a]) for a in "xyz"])
            out[(trace["meta"]["state"], trace["meta"]["epoch"])] = xyz
    return out
