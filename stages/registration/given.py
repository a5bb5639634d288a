"""``given``: a known 4x4 transform, inline or from a file, for pre-registered data."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from gdt_pipeline import Registration, StageContext, family_stage

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

    @model_validator(mode="after")
    def _one_source(self) -> GivenParams:
        if (self.transform is None) == (self.file is None):
            raise ValueError("set exactly one of `transform` or `file`")
        return self


def matrix_problems(params: GivenParams, base: Path) -> list[tuple[str, str]]:
    """The transform file, checked before a run: present, a file, a rigid 4x4 (whitespace text, .npy or .json)."""
    if params.file is None:
        return []
    path = (base / params.file).resolve()
    if path.is_dir():
        return [("file", f"{path} is a directory, not a file")]
    if not path.is_file():
        return [("file", f"transform file not found: {path}")]
    if path.stat().st_size > 1024 * 1024:
        return [("file", f"{path}: {path.stat().st_size:,} bytes is not a 4x4 transform")]
    try:
        check_rigid(load_matrix(path), str(path))
    except (ValueError, OSError, TypeError) as exc:  # numpy's and json's parse errors are ValueErrors
        return [("file", f"not a rigid 4x4 transform: {exc}")]
    return []


def load_matrix(path: Path) -> np.ndarray:
    """A 4x4 from whitespace text, .npy or .json."""
    if path.suffix == ".npy":
        return np.load(path, allow_pickle=False)
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
        problems = matrix_problems(p, ctx.epoch.workflow_dir)
        if problems:
            raise ValueError(f"given: {problems[0][1]}")
        t = check_rigid(load_matrix(path), str(path))
    else:
        t = np.asarray(p.transform, dtype=np.float64)
    return {"recent": [d.transformed(t) for d in ctx["recent"]], "registration": Registration(t, method="given")}


SPEC = family_stage("registrar", name="given", version="1.0.0", params=GivenParams, run=given,
                    validate=matrix_problems, requires=("recent",),
                    description="Apply a known 4x4 transform (inline or from a file).")
