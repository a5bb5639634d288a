"""Lean reads of a twin at an epoch: one element set at a time, one per-element value at a time, on request.

``read_element_set`` reads every primvar of a set at once, in float64 world coordinates; a reader that only
summarises a large twin (a report, a picture) would hold several times its point arrays. A ``LeanSet`` reads
nothing up front: each array comes from its primvar when asked for (points stay float32 relative to the set's
translate), so the caller can reduce it and drop it before asking for the next. A payload set (a large point set in
a layer of its own, see ``payloads``) also offers its decimated ``/Previews/<key>`` points and the rows of the set
they are, so that its own points need not be read at all.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from pxr import Usd, UsdGeom

from .elements import READ_PRIMVARS, identity_of, set_origin
from .errors import TwinStoreError
from .names import TWIN_PRIM
from .parts import is_parted, iter_point_parts, set_extent, set_points, set_values
from .payloads import PREVIEWS_PRIM, preview_rows

# what a lean read may ask for: its name -> the ElementSet field (``READ_PRIMVARS``: primvar and dtype) it reads
FIELDS: dict[str, str] = {"state": "state", "visible": "visible", "source_epoch": "source_epoch", "score": "score",
                          "uncertainty": "uncertainty_summary", "p_value": "p_value", "reason": "reason"}


def _primvar(prim: Usd.Prim, name: str) -> np.ndarray | None:
    """One per-element value of a prim (None when the prim has none); a one-prim set's arrays share USD's memory."""
    if name not in FIELDS:
        raise TwinStoreError(f"unknown per-element value {name!r} (known: {', '.join(FIELDS)})")
    return set_values(prim, FIELDS[name])


class LeanSet:
    """One element set of the twin at an epoch, each array read only when asked for (see the module docstring).

    Valid while the iteration that yielded it goes on (its prims belong to the stages the iteration holds)."""

    def __init__(self, prim: Usd.Prim, before: Usd.Prim | None, preview: Usd.Prim | None, first_epoch: bool) -> None:
        self._prim = prim
        self._before = before
        self._preview = preview
        self._first = first_epoch

    @property
    def key(self) -> str:
        """The set's key (prim name)."""
        return self._prim.GetName()

    @property
    def kind(self) -> str:
        """``mesh`` or ``points``."""
        return "mesh" if self._prim.IsA(UsdGeom.Mesh) else "points"

    @property
    def identity(self) -> dict[str, str] | None:
        """The set's identity outside the twin (part name, IFC GlobalId), if it has one."""
        return identity_of(self._prim)

    @property
    def new_here(self) -> bool:
        """Whether the set came in with this epoch (every set of the first epoch did)."""
        return self._first or self._before is None

    @property
    def has_preview(self) -> bool:
        """Whether the set is a payload set with a decimated preview (``preview``)."""
        return self._preview is not None

    def field(self, name: str) -> np.ndarray:
        """One per-element value (a name of ``FIELDS``) over all elements, read now."""
        value = _primvar(self._prim, name)
        if value is None:
            raise TwinStoreError(f"element set {self.key} has no {READ_PRIMVARS[FIELDS[name]][0]}")
        return value

    def field_before(self, name: str) -> np.ndarray | None:
        """The same value as it was at the previous epoch (None for a set that came in with this epoch)."""
        return None if self._before is None else _primvar(self._before, name)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World lower and upper corners of the set (from its extent; from its points where it has none)."""
        extent = set_extent(self._prim)
        local = np.asarray(extent if extent is not None else self.points()[0], dtype=np.float64)
        return local.min(axis=0) + set_origin(self._prim), local.max(axis=0) + set_origin(self._prim)

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """All points (mesh vertices) as float32 relative to the set's origin, and the origin (float64)."""
        return set_points(self._prim), set_origin(self._prim)

    def point_parts(self) -> tuple[Iterator[tuple[int, np.ndarray]], np.ndarray]:
        """The points as ``points`` gives them, but part by part for a set written in parts (``parts``): an
        iterator of (first row, float32 points relative to the origin), and the origin."""
        return iter_point_parts(self._prim), set_origin(self._prim)

    def faces(self) -> np.ndarray:
        """A mesh's triangles (F,3) into its points."""
        if self.kind != "mesh":
            raise TwinStoreError(f"element set {self.key} is a point set: it has no faces")
        return np.asarray(UsdGeom.Mesh(self._prim).GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)

    def preview(self, n_elements: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """For a payload set: its preview's points (float32, relative to the returned origin) and the rows of the
        set they are; None for a set without a preview (or one that does not match the set's ``n_elements``)."""
        if self._preview is None:
            return None
        rows = preview_rows(n_elements)
        local = np.asarray(UsdGeom.Points(self._preview).GetPointsAttr().Get(), dtype=np.float32).reshape(-1, 3)
        if len(local) != len(rows):
            return None
        return local, set_origin(self._preview), rows


def iter_lean_sets(stage: Usd.Stage, before: Usd.Stage | None) -> Iterator[LeanSet]:
    """The sets under ``/Twin`` of a composed stage, in prim order, each with its prim on the stage of the previous
    epoch (``before``; None at the first epoch) and its preview, if it has one."""
    twin = stage.GetPrimAtPath(TWIN_PRIM)
    for child in twin.GetChildren() if twin else []:
        if not child.IsA(UsdGeom.PointBased) and not is_parted(child):
            continue
        old = before.GetPrimAtPath(child.GetPath()) if before is not None else None
        preview = stage.GetPrimAtPath(f"{PREVIEWS_PRIM}/{child.GetName()}")
        yield LeanSet(child, old if old else None, preview if preview else None, before is None)
