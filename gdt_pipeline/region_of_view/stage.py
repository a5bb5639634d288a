"""The region-of-view factory: a builder finds the volume its sensors measured and the stations inside it; the stage
made around it judges every reference element inside that volume with the shared sight test (``look``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from ..plugins import StageContext, StageSpec, family_stage
from ..types import RegionOfView
from .depth import Station
from .look import look
from .params import SightParams


@dataclass(frozen=True)
class Volume:
    """What a region-of-view builder found: the closed surfaces its sensors measured inside (``region``, a
    ``RegionOfView`` with its ``parts`` and no judgements yet), one line per part saying how it was found, and the
    stations the sight test looks from (None: each recent dataset's viewpoints, with the whole volume as theirs)."""

    region: RegionOfView
    parts: Sequence[str]
    stations: Sequence[Station] | None = None


Build = Callable[[StageContext], Volume]


def rov_stage(*, name: str, build: Build, params: type[SightParams], version: str, description: str = ""
              ) -> StageSpec:
    """A region-of-view stage from a builder ``build(ctx) -> Volume``; ``params`` extends ``SightParams`` (how
    sight is judged), so every builder offers the same sight tests. It reads the recent data (and the reference,
    when there is one) and provides the ``rov`` slot."""
    if not (isinstance(params, type) and issubclass(params, SightParams)):
        raise TypeError(f"region-of-view stage {name!r}: its params must extend SightParams")

    def run(ctx: StageContext) -> dict[str, Any]:
        volume = build(ctx)
        stations = None if volume.stations is None else list(volume.stations)
        return look(ctx, volume.region, list(volume.parts), stations)

    return family_stage("rov", name=name, version=version, params=params, run=run, optional=("reference",),
                        description=description)
