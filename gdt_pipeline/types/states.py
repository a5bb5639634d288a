"""Roles, kinds, change states and fusion reasons: the codes the twin stores, named from the twin store's tables."""

from __future__ import annotations

import enum
from typing import Literal

from twin_store import REASON_NAMES, STATE_NAMES

Role = Literal["as-designed", "as-is"]
Kind = Literal["mesh", "points"]

# The twin store owns the names it writes into every layer; the engine's codes are built from its tables so that the
# two can never disagree.
ChangeState = enum.IntEnum("ChangeState", [(n.upper(), i) for i, n in enumerate(STATE_NAMES)], module=__name__)
ChangeState.__doc__ = "Per-element change state; the codes are the ones stored in the twin (``gdt:changeState``)."
FusionReason = enum.IntEnum("FusionReason", [(n.upper(), i) for i, n in enumerate(REASON_NAMES)], module=__name__)
FusionReason.__doc__ = ("Why an element is (or is not) in the composite after an epoch's fusion; the codes are the "
                        "ones stored in the twin (``gdt:fusionReason``).")
