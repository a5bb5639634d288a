"""Thresholds: turn scores into a change mask. An element with no correspondence (NaN score) is always changed: it
comes in as new, never silently dropped.

- ``fixed``: changed where score > τ;
- ``tolerance_multiple``: τ = k·ε_T, the paper's initial value, with ε_T the integration tolerance the distance
  stage reports;
- ``significance``: changed where the test's p-value < α (for measures that have p-values: hotelling, welch_m3c2);
- ``calibrated_threshold`` (the issue's "calibrated"; the name ``calibrated`` is the uncertainty estimator's):
  τ for a chosen false-alarm rate, from the scores of simulated unchanged pairs drawn from the two
  actual uncertainty models (seeded); the rate achieved on an independent simulation is reported.
"""

from __future__ import annotations

from gdt_pipeline import StageSpec, hookimpl

from . import calibrated_threshold, rules
from .calibrated_threshold import CalibratedParams
from .rules import FixedParams, SignificanceParams, ToleranceMultipleParams

__all__ = ["CalibratedParams", "FixedParams", "SignificanceParams", "ToleranceMultipleParams", "gdt_stages"]


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in thresholds."""
    return [rules.FIXED, rules.TOLERANCE_MULTIPLE, rules.SIGNIFICANCE, calibrated_threshold.SPEC]
