"""The workflow a suite scene ships with: the default chain, every stage at its default parameters except the ones
the scene fixes (the CAD's ±0.5 mm tolerance boxes, the true sensor profile, a 1 % false-alarm rate)."""

from __future__ import annotations

import json
from pathlib import Path

TWIN_DIR = "twin"  # beside the scene's files: a scene directory carries its own twin once run
CAD_HALF_WIDTH = 0.0005  # m: the CAD's tolerance box half width on every axis

STAGES = f"""stages:
  - uses: constant
    role: as-designed
    with: {{model: box, half_widths: [{CAD_HALF_WIDTH}, {CAD_HALF_WIDTH}, {CAD_HALF_WIDTH}]}}
  - uses: identity
    role: as-is
  - uses: sensor_model
    role: as-is
    with: {{profile: PROFILE}}
  - uses: sensor_frustum
    role: as-is
  - uses: auto
    role: as-is
  - uses: bhattacharyya
    role: as-is
  - uses: calibrated_threshold
    role: as-is
    with: {{false_alarm: 0.01}}
  - uses: most_reliable
"""


def _vec(v: list[float]) -> str:
    return "[" + ", ".join(repr(float(x)) for x in v) + "]"


def write_workflow(root: Path, suite: str, seed: int, cad: list[Path], scans: list[Path],
                   viewpoints: list[list[float]], profile_file: str, as_mesh: bool) -> Path:
    """Write ``workflow.yaml`` into the scene directory (paths relative to it) and return its path."""
    kind = ", kind: mesh" if as_mesh else ""
    lines = [
        f"# A random scene of the {suite!r} suite (seed {seed}), written by gdt_pipeline.simulation.suite.",
        "# Run: gdt run workflow.yaml (in this directory); gdt eval --suite scores whole suites.",
        f"name: suite-{suite}-{seed}",
        "description: " + json.dumps(f"Random {suite} scene (seed {seed}): CAD (E0) and a simulated scan with parts "
                                     f"added, removed and moved (E1)."),
        f"twin: {TWIN_DIR}",
        "units: m",
        "epochs:",
        "  - id: E0",
        "    role: as-designed",
        "    inputs:",
        *(f"      - {{path: {p.name}}}" for p in cad),
        "  - id: E1",
        "    role: as-is",
        "    inputs:",
        *(f"      - {{path: {p.name}, viewpoints: [{_vec(vp)}]{kind}}}" for p, vp in zip(scans, viewpoints,
                                                                                        strict=True)),
    ]
    path = root / "workflow.yaml"
    path.write_text("\n".join(lines) + "\n" + STAGES.replace("PROFILE", profile_file), encoding="utf-8")
    return path
