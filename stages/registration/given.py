"""``given``: a known 4x4 transform, inline or from a file, for pre-registered data."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from gdt_pipeline import Registration, StageContext

from ._icp import check_rigid


class GivenParams(BaseModel):
    """A known transform, inline or from a file."""

    model_config = ConfigDict(extra="forbid")
    transform: list[list[float]] | None = Field(None, description="4x4 row-major matrix.")
    file: str | None = Field(None, description="File with the 4x4 (whitespace text, .npy or .json), relative to "
                                               "the workflow.")

    @field_validator("transform")
    @classmethod
    def _rigid(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        if v is not None:
            check_rigid(np.asarray(v), "transform")
        return v


def load_matrix(path: Path) -> np.ndarray:
    """A 4x4 from whitespace text, .npy or .json."""
    if path.suffix == ".npy":
        return np.load(path)
    if path.suffix == ".json":
        return np.asarray(json.loads(path.read_text()), dtype=np.float64)
    return np.loadtxt(path)


def given(ctx: StageContext) -> dict[str, Any]:
    """The recent data moved by the known transform."""
    p = ctx.params
    if (p.transform is None) == (p.file is None):
        raise ValueError("given: set exactly one of `transform` or `file`")
    if p.file is not None:
        path = (ctx.epoch.workflow_dir / p.file).resolve()
        if not path.is_file():
            raise ValueError(f"given: transform file not found: {path}")
        t = check_rigid(load_matrix(path), str(path))
    else:
        t = np.asarray(p.transform, dtype=np.float64)
    return {"recent": [d.transformed(t) for d in ctx["recent"]], "registration": Registration(t, method="given")}
