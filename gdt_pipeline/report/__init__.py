"""``gdt report``: one self-contained HTML page of a twin at an epoch, for reading offline in any browser.

It holds a 3-D view of the composite coloured by change state (plotly.js, embedded), the epoch's segments (a click
frames one in the view), the histograms of the change scores with the threshold and of the uncertainty per
dataset, and the epoch's provenance. Reading is bounded for twins too large for a page: sets are read one at a time
and one value at a time (``twin_store.TwinStore.iter_sets``), points are subsampled on a voxel grid to the budget
as they come in, and payload sets are drawn from their decimated previews (docs/report.md has the figures).

Modules: ``scene`` (what the view shows), ``voxels`` (the subsample), ``histograms``, ``figures`` (plotly JSON),
``tables`` (HTML tables), ``compose`` (the sections), ``page`` (the file, plotly.js and its licence).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from twin_store import TwinStore, TwinStoreError

from ..names import unit_name
from .compose import page_parts
from .histograms import epoch_histograms
from .page import plotly_asset, write_page
from .scene import census, scene_data

DEFAULT_BUDGET = 500_000

__all__ = ["DEFAULT_BUDGET", "ReportSummary", "default_output", "write_report"]


@dataclass(frozen=True)
class ReportSummary:
    """What ``write_report`` wrote: the file, its size, the points drawn of those the view would show, the time."""

    path: Path
    bytes: int
    points_shown: int
    points_total: int
    seconds: float
    epoch: str = ""


def default_output(twin: Path) -> Path:
    """``<twin folder name>_report.html`` beside the twin folder."""
    twin = Path(twin)
    return twin.absolute().parent / f"{twin.absolute().name}_report.html"


def write_report(twin: Path, out: Path, *, epoch: str | None = None, budget: int = DEFAULT_BUDGET) -> ReportSummary:
    """Write the HTML report of ``twin`` at ``epoch`` (default: the latest) to ``out``."""
    t0 = time.perf_counter()
    if budget < 0:
        raise ValueError(f"the point budget must be 0 or more, not {budget}")
    store = TwinStore.open(twin)
    epochs = store.epochs()
    if not epochs:
        raise TwinStoreError(f"twin {twin} has no epochs yet")
    epoch = epochs[-1] if epoch is None else epoch
    if epoch not in epochs:
        raise TwinStoreError(f"twin {twin} has no epoch {epoch!r} (epochs: {', '.join(epochs)})")
    asset = plotly_asset()  # before the reading: a missing plotly is said at once
    provenance = store.provenance(epoch)
    units = unit_name(store.meters_per_unit())
    sets, lower, upper = census(store, epoch)
    scene = scene_data(store, epoch, sets, (lower, upper), budget)
    parts = page_parts(
        twin=Path(twin).name or str(twin), epoch=epoch, epochs=epochs, provenance=provenance, sets=sets, scene=scene,
        segments=store.read_segments(epoch, members=False),
        scores=epoch_histograms(store, epoch, "score", provenance),
        sigmas=epoch_histograms(store, epoch, "uncertainty"),
        budget=budget, units=units, up_axis=str((provenance.get("workflow") or {}).get("up_axis", "Z")))
    size = write_page(Path(out), parts, asset)
    return ReportSummary(Path(out), size, scene.points_shown, scene.points_total, time.perf_counter() - t0, epoch)
