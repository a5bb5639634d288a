"""Roles, kinds, change states and fusion reasons: the codes the twin stores, named from the twin store's tables."""

from __future__ import annotations

import enum
from typing import Literal

from twin_store import REASON_NAMES, STATE_NAMES

Role = Literal["as-designed", "as-is"]
Kind = Literal["mesh", "points"]



class ChangeState(enum.IntEnum):
    """Per-element change state; the codes are the ones stored in the twin (``gdt:changeState``)."""

    UNCHANGED = 0
    NEW = 1
    REMOVED = 2
    OUTSIDE_ROV = 3
    NOT_COMPARABLE = 4


class FusionReason(enum.IntEnum):
    """Why an element is (or is not) in the composite after an epoch's fusion; the codes are the ones stored in the
    twin (``gdt:fusionReason``)."""

    BASELINE = 0
    KEPT = 1
    NEW = 2
    REMOVED = 3
    OUTSIDE_ROV = 4
    REPLACED = 5
    REPLACES = 6
    KNOWN_MORE_PRECISE = 7
    DESIGN_STAYS = 8
    KNOWN_STAYS = 9
    EXTENDS = 10


# The twin store owns the names it writes into every layer; the engine's codes are spelt out for type checkers and
# checked against its tables here, so that the two can never disagree.
for codes, names in ((ChangeState, STATE_NAMES), (FusionReason, REASON_NAMES)):
    if [c.name.lower() for c in codes] != list(names):
        raise ImportError(f"{codes.__name__} {[c.name for c in codes]} disagrees with the twin store's {names}")
