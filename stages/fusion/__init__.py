"""Fusion. Here ``keep_unchanged``: the known data stays, the changed elements of the new data come in, and the
unchanged new elements are kept in the twin's history but hidden (the known data already images them).

Change states are per epoch: elements carried over from an earlier epoch go back to "unchanged" unless this epoch
changes them; the first epoch is the baseline, so its elements are "unchanged" too. Removal needs the region of
view: with a region-of-view stage in the chain, a reference element in view that no recent data matches is
"removed" and leaves the composite (it stays in the history), and one outside the region of view is marked so and
kept as it was (never removed)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from gdt_pipeline import ChangeState, Composite, CompositeItem, StageContext, StageSpec, hookimpl


class KeepUnchangedParams(BaseModel):
    """``keep_unchanged`` has no parameters."""

    model_config = ConfigDict(extra="forbid")


def _check(available: frozenset[str]) -> str | None:
    if "reference" in available and "change" not in available:
        return "fusion 'keep_unchanged' needs slot 'change' once a reference exists (add distance and threshold stages)"
    return None


def _keep_unchanged(ctx: StageContext) -> dict[str, Any]:
    reference = ctx.get("reference") or Composite()
    changes = {c.query: c for c in ctx.get("change") or []}
    epoch = ctx.epoch
    items: list[CompositeItem] = []
    rov = ctx.get("rov")
    for it in reference.items:
        state = np.where(it.state == ChangeState.NEW, ChangeState.UNCHANGED, it.state).astype(np.uint8)
        visible = it.visible
        if rov is not None and it.key in rov.in_view:
            view, matched = rov.in_view[it.key], rov.matched[it.key]
            removed = view & ~matched & it.visible
            state = np.where(state == ChangeState.OUTSIDE_ROV, ChangeState.UNCHANGED, state).astype(np.uint8)
            state[it.visible & ~view] = ChangeState.OUTSIDE_ROV
            state[removed] = ChangeState.REMOVED
            visible = it.visible & ~removed
        items.append(dataclasses.replace(it, state=state, visible=visible))
    for qi, ds in enumerate(ctx["recent"]):
        n = ds.n_elements
        ch = changes.get(qi)
        if ch is None and reference.items:
            raise ValueError(f"dataset {ds.name!r} has no change result although a reference exists")
        p_value = None
        if ch is None:
            visible = np.ones(n, dtype=bool)
            state = np.full(n, ChangeState.UNCHANGED, dtype=np.uint8)
            score = np.full(n, np.nan)
        else:
            visible, state, score, p_value = ch.mask, ch.state, ch.score, ch.p_value
        items.append(CompositeItem(key=f"{epoch.id}_{ds.name}", dataset=ds, epoch=epoch.id, state=state, score=score,
                                   source_epoch=np.full(n, epoch.index, dtype=np.int32), visible=visible,
                                   p_value=p_value))
    return {"composite": Composite(tuple(items))}


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in fusions."""
    return [StageSpec(name="keep_unchanged", family="fusion", version="1.1.0", params=KeepUnchangedParams,
                      run=_keep_unchanged, requires=("recent",), optional=("reference", "change", "rov"),
                      provides=("composite",), check=_check,
                      description="Known data stays; changed new elements come in; unchanged new ones are hidden.")]
