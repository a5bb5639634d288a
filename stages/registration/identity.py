"""``identity``: the recent data is already registered."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from gdt_pipeline import Registration, StageContext, family_stage


class IdentityParams(BaseModel):
    """``identity`` has no parameters."""

    model_config = ConfigDict(extra="forbid")


def identity(ctx: StageContext) -> dict[str, Any]:
    """The recent data where it is, with the identity transform."""
    return {"recent": list(ctx["recent"]), "registration": Registration(np.eye(4), method="identity")}


SPEC = family_stage("registrar", name="identity", version="1.0.0", params=IdentityParams, run=identity,
                    requires=("recent",), description="Keep the recent data where it is (pre-registered input).")
