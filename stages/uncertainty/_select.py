"""Which recent datasets an uncertainty stage applies to (every estimator's ``datasets`` parameter)."""

from __future__ import annotations

from collections.abc import Callable

from gdt_pipeline import Dataset, StageContext


def selected(ctx: StageContext) -> tuple[list[Dataset], set[str]]:
    """The recent datasets, and the names this stage applies to (its ``datasets`` param, default all)."""
    recent = list(ctx["recent"])
    names = ctx.params.datasets
    if names is None:
        return recent, {d.name for d in recent}
    unknown = sorted(set(names) - {d.name for d in recent})
    if unknown:
        raise ValueError(f"datasets {unknown} are not in this epoch (have: {[d.name for d in recent]})")
    return recent, set(names)


def map_selected(ctx: StageContext, estimate: Callable[[Dataset], Dataset]) -> list[Dataset]:
    """The recent datasets in order, each selected one replaced by ``estimate(dataset)``, the others as they are."""
    recent, names = selected(ctx)
    return [estimate(ds) if ds.name in names else ds for ds in recent]
