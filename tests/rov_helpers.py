"""What the region-of-view tests share: a stage context for one epoch and a CAD mesh as a visible reference item."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import trimesh

from gdt_pipeline import Composite, CompositeItem, Dataset, EpochInfo
from gdt_pipeline.plugins import Registry, StageContext


def stage_ctx(registry: Registry, stage: str, params: dict, recent: list[Dataset], reference: Composite,
              workflow_dir: Path) -> StageContext:
    """A context for ``stage`` in epoch E1 with these recent datasets and this reference."""
    spec = registry.get(stage)
    info = EpochInfo(id="E1", index=1, role="as-is", seed=0, workflow_dir=workflow_dir, units="m")
    slots = {"recent": recent, "reference": reference, "epoch": info}
    return StageContext(stage=spec, params=spec.params(**params), slots=slots, epoch=info,
                        rng=np.random.default_rng(0), seed=0, log=logging.getLogger("test"))


def cad_item(key: str, mesh: trimesh.Trimesh) -> CompositeItem:
    """A mesh as an E0 reference item, every facet visible and unchanged."""
    ds = Dataset(key, "as-designed", mesh.vertices, faces=mesh.faces)
    n = len(mesh.faces)
    return CompositeItem(key, ds, "E0", np.zeros(n, np.uint8), np.full(n, np.nan), np.zeros(n, np.int32),
                         np.ones(n, bool))


def plant_room() -> list[trimesh.Trimesh]:
    """Boxes of a plant room seen at many incidences: a floor, a back wall and three cabinets turned about z."""
    parts = [trimesh.creation.box(extents=(6.0, 6.0, 0.1)), trimesh.creation.box(extents=(0.1, 6.0, 3.0))]
    parts[0].apply_translation((0, 0, -0.05))
    parts[1].apply_translation((-3.0, 0, 1.5))
    for k, (x, y, turn) in enumerate(((-1.5, -1.5, 0.3), (-1.8, 1.2, 0.9), (0.2, 0.4, 0.0))):
        box = trimesh.creation.box(extents=(0.8, 0.6, 1.2 + 0.3 * k))
        box.apply_transform(trimesh.transformations.rotation_matrix(turn, (0, 0, 1)))
        box.apply_translation((x, y, 0.6 + 0.15 * k))
        parts.append(box)
    return parts
