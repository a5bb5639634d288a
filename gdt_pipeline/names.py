"""The engine's tables of names, each written once: units, slots, and the identifiers made from file names.

The change-state and fusion-reason names are the twin store's (it writes them into every layer); the engine's enums
in ``gdt_pipeline.types`` are built from those tables.
"""

from __future__ import annotations

from typing import Literal

# Length units a workflow or an input may declare, in metres.
UNITS: dict[str, float] = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001, "um": 1e-6, "in": 0.0254, "ft": 0.3048}
# The same names as a type, for pydantic models (workflow inputs, sensor profiles).
Units = Literal[tuple(UNITS)]


def unit_name(meters_per_unit: float) -> str:
    """The short name of a unit (``m``, ``mm``...) from its size in metres, or the size itself when it has none."""
    return next((name for name, m in UNITS.items() if abs(m - meters_per_unit) <= 1e-12 * m), f"{meters_per_unit:g} m")


def identifier(stem: str) -> str:
    """A USD-safe identifier from a file stem: non-alphanumerics become ``_``, a leading digit gets a ``_``."""
    # ASCII only: str.isalnum() passes "ü", which USD's identifiers refuse (an IFC wall named "Wand Süd")
    out = "".join(ch if (ch.isascii() and ch.isalnum()) or ch == "_" else "_" for ch in stem)
    return out if out and not out[0].isdigit() else f"_{out}"
