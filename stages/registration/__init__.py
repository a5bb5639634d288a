"""Registrars. Here only ``identity``, for data that is already in the twin's frame; GICP and friends come with the
registration issue."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from gdt_pipeline import Registration, StageContext, StageSpec, hookimpl


class IdentityParams(BaseModel):
    """``identity`` has no parameters."""

    model_config = ConfigDict(extra="forbid")


def _identity(ctx: StageContext) -> dict[str, Any]:
    return {"recent": list(ctx["recent"]), "registration": Registration(np.eye(4), method="identity")}


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in registrars."""
    return [StageSpec(name="identity", family="registrar", version="1.0.0", params=IdentityParams, run=_identity,
                      requires=("recent",), provides=("recent", "registration"),
                      description="Keep the recent data where it is (pre-registered input).")]
