"""The file-based twin: a USD root stage with one sublayer per epoch, written atomically.

Layout::

    twin/
      twin.usda        root: subLayers strongest first (epochs/E1.usdc, epochs/E0.usdc), metersPerUnit, upAxis
      epochs/E0.usdc   only the opinions of epoch E0
      epochs/E1.usdc   only the opinions of epoch E1: new prims, and overrides of earlier prims' per-element values

Each element set is one prim ``/Twin/<key>`` (UsdGeom.Mesh or UsdGeom.Points). Points are stored as float32 relative
to an ``xformOp:translate`` (double) at the set's centre, so georeferenced coordinates (UTM metres) keep their
precision. Per-element values are primvars in the ``gdt:`` namespace with interpolation ``vertex`` (points) or
``uniform`` (facets), restated in every layer that writes them.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

STATE_NAMES: tuple[str, ...] = ("unchanged", "new", "removed", "outside_rov")
STATE_COLORS = np.array([[0.7, 0.7, 0.7], [0.1, 0.75, 0.2], [0.85, 0.1, 0.1], [0.3, 0.45, 0.9]], dtype=np.float32)
ROOT_NAME = "twin.usda"
EPOCH_DIR = "epochs"
ROV_PRIM = "/RegionsOfView"
SEGMENTS_PRIM = "/Segments"
TWIN_PRIM = "/Twin"

_DOC_COV = "Per-element positional covariance, 6 floats per element in the order xx xy xz yy yz zz (twin units²)."
# why an element is (or is not) in the composite after an epoch's fusion; the codes are gdt:fusionReason
REASON_NAMES: tuple[str, ...] = (
    "baseline",            # 0: the element came with the first epoch (or no fusion decided about it)
    "kept",                # 1: known element, still in the composite
    "new",                 # 2: changed element of the epoch's data, came in
    "removed",             # 3: known element in the region of view that no recent data matches: hidden
    "outside_rov",         # 4: known element outside the region of view: kept as it was
    "replaced",            # 5: known element imaged by more precise (or, by policy, newer) data: hidden
    "replaces",            # 6: unchanged recent element that took the place of known data
    "known_more_precise",  # 7: unchanged recent element hidden: the known data it images is as precise or better
    "design_stays",        # 8: unchanged recent element hidden: it images design (CAD) geometry, which stays
    "known_stays",         # 9: unchanged recent element hidden: the policy keeps known data (or it images none)
)
_DOC_REASON = ("Per-element fusion reason code: " + ", ".join(f"{i}={n}" for i, n in enumerate(REASON_NAMES))
               + ". Hidden elements keep the reason they left with.")
_DOC_STATE = "Per-element change state code: " + ", ".join(f"{i}={n}" for i, n in enumerate(STATE_NAMES)) + "."


class TwinStoreError(Exception):
    """A clear, user-facing twin store error naming the twin path, epoch or key."""


@dataclass(frozen=True)
class ElementSet:
    """One dataset of the twin: geometry plus per-element uncertainty, change and history values.

    An element is a facet for meshes and a point for point sets.
    """

    key: str
    kind: str
    points: np.ndarray
    faces: np.ndarray | None
    uncertainty_model: str
    covariance: np.ndarray | None
    half_widths: np.ndarray | None
    rotation: np.ndarray | None
    uncertainty_summary: np.ndarray
    state: np.ndarray
    score: np.ndarray
    source_epoch: np.ndarray
    visible: np.ndarray
    ids: np.ndarray | None = None
    display_color: np.ndarray | None = None  # (E,3) in 0..1; default: baked from the change state
    p_value: np.ndarray | None = None  # (E,) p-value of the change test, where the measure has one
    reason: np.ndarray | None = None  # (E,) uint8 fusion reason code (REASON_NAMES)
    reason_ratio: np.ndarray | None = None  # (E,) the numbers behind the reason: √det Σ new / known, NaN if none

    def __post_init__(self) -> None:
        if not Tf.IsValidIdentifier(self.key):
            raise TwinStoreError(f"element set key {self.key!r} is not a valid USD identifier")
        if self.kind not in ("mesh", "points"):
            raise TwinStoreError(f"{self.key}: kind must be 'mesh' or 'points', not {self.kind!r}")
        if self.uncertainty_model not in ("gaussian", "box", "mixture", "none"):
            raise TwinStoreError(f"{self.key}: unknown uncertainty model {self.uncertainty_model!r}")
        pts = np.asarray(self.points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise TwinStoreError(f"{self.key}: points must be (V,3), got {pts.shape}")
        if self.kind == "mesh":
            if self.faces is None or np.asarray(self.faces).ndim != 2 or np.asarray(self.faces).shape[1] != 3:
                raise TwinStoreError(f"{self.key}: a mesh needs faces of shape (F,3)")
            n = len(self.faces)
        else:
            if self.faces is not None:
                raise TwinStoreError(f"{self.key}: a point set has no faces")
            n = len(pts)
        shapes = {"uncertainty_summary": (n,), "state": (n,), "score": (n,), "source_epoch": (n,), "visible": (n,),
                  "covariance": (n, 6), "half_widths": (n, 3), "rotation": (n, 3, 3), "ids": (n,),
                  "display_color": (n, 3), "p_value": (n,), "reason": (n,), "reason_ratio": (n,)}
        for name, shape in shapes.items():
            value = getattr(self, name)
            if value is not None and np.shape(value) != shape:
                raise TwinStoreError(f"{self.key}: {name} must have shape {shape}, got {np.shape(value)}")
        if self.uncertainty_model in ("gaussian", "mixture") and self.covariance is None:
            raise TwinStoreError(f"{self.key}: a {self.uncertainty_model} uncertainty needs covariance")
        if self.uncertainty_model == "box" and self.half_widths is None:
            raise TwinStoreError(f"{self.key}: a box uncertainty needs half_widths")

    @property
    def n_elements(self) -> int:
        """Number of elements (facets of a mesh, points of a point set)."""
        return len(self.faces) if self.faces is not None else len(self.points)


def lock_path(twin: Path) -> Path:
    """The writer lock of a twin: a file beside the twin folder (the folder itself may be swapped whole)."""
    twin = Path(twin).resolve()
    return twin.parent / f".{twin.name}.lock"


@contextlib.contextmanager
def writer_lock(twin: str | Path) -> Iterator[None]:
    """Hold the twin's writer lock; a second writer gets a clear TwinStoreError instead of waiting or corrupting."""
    path = lock_path(Path(twin))
    path.parent.mkdir(parents=True, exist_ok=True)
    fh = open(path, "a+", encoding="utf-8")  # noqa: SIM115  (closed in finally; flock needs the open file)
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "unknown process"
            raise TwinStoreError(f"twin {Path(twin).resolve()} is being written by another writer ({holder}); "
                                 f"wait for it to finish (lock: {path})") from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} since {time.strftime('%Y-%m-%dT%H:%M:%S')}")
        fh.flush()
        yield
    finally:
        with contextlib.suppress(OSError):
            fh.truncate(0)
        fh.close()  # closing releases the flock


def _fsync(path: Path) -> None:
    """Flush a file, or a folder's entries after a rename, to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _export_atomic(layer: Sdf.Layer, target: Path) -> None:
    """Export a layer to a temp file with the same extension (USD picks the format by it), fsync, rename."""
    tmp = target.with_name(f".{target.stem}.tmp-{os.getpid()}{target.suffix}")
    if not layer.Export(str(tmp)):
        raise TwinStoreError(f"could not write {tmp}")
    _fsync(tmp)
    os.replace(tmp, target)
    _fsync(target.parent)
    cached = Sdf.Layer.Find(str(target))
    if cached is not None:
        cached.Reload(force=True)


def _open_layer(path: Path) -> Sdf.Layer:
    layer = Sdf.Layer.Find(str(path))
    if layer is not None:
        layer.Reload(force=True)
        return layer
    layer = Sdf.Layer.FindOrOpen(str(path))
    if layer is None:
        raise TwinStoreError(f"cannot open USD layer {path}")
    return layer


def _face_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = points[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def _values(es: ElementSet) -> dict[str, tuple[Any, Any, np.ndarray, int, str | None]]:
    """Per-element primvars of a set: name -> (value type, interpolation, array, element size, documentation)."""
    interp = UsdGeom.Tokens.uniform if es.kind == "mesh" else UsdGeom.Tokens.vertex
    state = np.asarray(es.state, dtype=np.uint8)
    out: dict[str, tuple[Any, Any, np.ndarray, int, str | None]] = {
        "gdt:uncertainty": (Sdf.ValueTypeNames.FloatArray, interp,
                            np.asarray(es.uncertainty_summary, dtype=np.float32), 1,
                            "Scalar uncertainty per element for display: RMS standard deviation (twin units)."),
        "gdt:changeScore": (Sdf.ValueTypeNames.FloatArray, interp, np.asarray(es.score, dtype=np.float32), 1,
                            "Change score per element (dissimilarity); NaN where not scored."),
        "gdt:changeState": (Sdf.ValueTypeNames.UCharArray, interp, state, 1, _DOC_STATE),
        "gdt:sourceEpoch": (Sdf.ValueTypeNames.IntArray, interp, np.asarray(es.source_epoch, dtype=np.int32), 1,
                            "Index of the epoch that supplied the element."),
        "gdt:visible": (Sdf.ValueTypeNames.BoolArray, interp, np.asarray(es.visible, dtype=bool), 1,
                        "Element is part of the composite at this epoch; hidden elements stay in the history."),
        "displayColor": (Sdf.ValueTypeNames.Color3fArray, interp,
                         STATE_COLORS[np.minimum(state, len(STATE_COLORS) - 1)] if es.display_color is None
                         else np.asarray(es.display_color, dtype=np.float32), 1, None),
    }
    if es.covariance is not None:
        out["gdt:covariance"] = (Sdf.ValueTypeNames.FloatArray, interp,
                                 np.asarray(es.covariance, dtype=np.float32).reshape(-1), 6, _DOC_COV)
    if es.half_widths is not None:
        out["gdt:halfWidths"] = (Sdf.ValueTypeNames.Float3Array, interp, np.asarray(es.half_widths, np.float32), 1,
                                 "GUM rectangular error limits: box half-widths per element (twin units).")
    if es.p_value is not None:
        out["gdt:pValue"] = (Sdf.ValueTypeNames.FloatArray, interp, np.asarray(es.p_value, dtype=np.float32), 1,
                             "p-value of the change test per element (NaN where not tested).")
    if es.reason is not None:
        out["gdt:fusionReason"] = (Sdf.ValueTypeNames.UCharArray, interp, np.asarray(es.reason, dtype=np.uint8), 1,
                                   _DOC_REASON)
    if es.reason_ratio is not None:
        out["gdt:fusionRatio"] = (Sdf.ValueTypeNames.FloatArray, interp,
                                  np.asarray(es.reason_ratio, dtype=np.float32), 1,
                                  "The fusion rule's number per element: √det Σ of the new data over that of the "
                                  "known data it was compared with (replaced, replaces, known_more_precise); NaN "
                                  "where no comparison was made.")
    if es.rotation is not None:
        out["gdt:rotation"] = (Sdf.ValueTypeNames.FloatArray, interp,
                               np.asarray(es.rotation, dtype=np.float32).reshape(-1), 9,
                               "Box axes per element: a row-major 3x3 rotation whose columns are the axes.")
    return out


def _point_widths(points: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Per-point widths: 1/500 of the set's diagonal, and 0 for hidden points, so that plain viewers hide them."""
    diag = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) if len(points) else 0.0
    return np.where(np.asarray(visible, dtype=bool), diag / 500.0 if diag > 0 else 0.002, 0.0).astype(np.float32)


def _vt(type_name: Any, arr: np.ndarray) -> Any:
    if type_name == Sdf.ValueTypeNames.BoolArray:
        return Vt.BoolArray([bool(v) for v in arr]) if arr.size < 64 else Vt.BoolArray.FromNumpy(arr)
    return type_name.type.pythonClass.FromNumpy(np.ascontiguousarray(arr))


def _same(old: Any, new: np.ndarray) -> bool:
    if old is None:
        return False
    a = np.asarray(old)
    if a.shape != new.shape and a.size == new.size:
        a = a.reshape(new.shape)
    return a.shape == new.shape and bool(np.array_equal(a, new, equal_nan=a.dtype.kind == "f"))


class TwinStore:
    """A twin folder: create or open it, write an epoch, read the composite at any epoch and its provenance."""

    def __init__(self, path: Path, *, lock: bool = True) -> None:
        self._path = path
        self._lock = lock
        self._holding = False

    @property
    def path(self) -> Path:
        """The twin folder."""
        return self._path

    @property
    def root_path(self) -> Path:
        """The root layer, twin.usda."""
        return self._path / ROOT_NAME

    @classmethod
    def create(cls, path: str | Path, *, meters_per_unit: float = 1.0, up_axis: str = "Z",
               overwrite: bool = False, lock: bool = True) -> TwinStore:
        """Create an empty twin folder (root layer with no epochs yet).

        ``lock=False`` is for a private folder whose caller already holds the lock of the twin it will become.
        """
        path = Path(path)
        if (path / ROOT_NAME).exists() and not overwrite:
            raise TwinStoreError(f"twin {path} already exists")
        if path.exists() and any(path.iterdir()) and not (path / ROOT_NAME).exists():
            raise TwinStoreError(f"{path} exists, is not empty and is not a twin")
        if up_axis not in ("Y", "Z"):
            raise TwinStoreError(f"up axis must be 'Y' or 'Z', not {up_axis!r}")
        (path / EPOCH_DIR).mkdir(parents=True, exist_ok=True)
        root = Sdf.Layer.CreateAnonymous("root.usda")
        stage = Usd.Stage.Open(root)
        UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up_axis == "Z" else UsdGeom.Tokens.y)
        root.defaultPrim = TWIN_PRIM.strip("/")
        root.documentation = "gdt-pipeline twin: one sublayer per epoch, strongest first."
        _export_atomic(root, path / ROOT_NAME)
        return cls(path, lock=lock)

    @classmethod
    def open(cls, path: str | Path) -> TwinStore:
        """Open an existing twin folder."""
        path = Path(path)
        if not (path / ROOT_NAME).is_file():
            raise TwinStoreError(f"{path} is not a twin (no {ROOT_NAME})")
        return cls(path)

    @contextlib.contextmanager
    def writing(self) -> Iterator[TwinStore]:
        """Hold the writer lock across several epoch writes (write_epoch takes it itself otherwise)."""
        if self._holding or not self._lock:
            yield self
            return
        with writer_lock(self._path):
            self._holding = True
            try:
                yield self
            finally:
                self._holding = False

    def _root(self) -> Sdf.Layer:
        return _open_layer(self.root_path)

    def epochs(self) -> list[str]:
        """Epoch ids, oldest first."""
        root = self._root()  # keep the layer alive while its list proxy is read
        return [Path(p).stem for p in reversed(list(root.subLayerPaths))]

    def _epoch_file(self, epoch_id: str) -> Path:
        return self._path / EPOCH_DIR / f"{epoch_id}.usdc"

    def _stage_upto(self, epochs: Sequence[str], extra: Sdf.Layer | None = None) -> Usd.Stage:
        """A stage over an in-memory root holding the given epochs' layers (and an extra strongest layer)."""
        root = self._root()
        anon = Sdf.Layer.CreateAnonymous("compose.usda")
        anon.TransferContent(root)
        paths = [str(self._epoch_file(e)) for e in reversed(list(epochs))]
        anon.subLayerPaths.clear()
        for p in ([extra.identifier] if extra is not None else []) + paths:
            anon.subLayerPaths.append(p)
        for p in paths:
            _open_layer(Path(p))
        return Usd.Stage.Open(anon)

    def write_epoch(self, epoch_id: str, elements: Sequence[ElementSet], provenance: dict,
                    region_of_view: tuple[np.ndarray, np.ndarray] | None = None,
                    segments: Sequence[dict] = ()) -> Path:
        """Write one epoch layer holding the composite after this epoch (and the region of view its sensors
        measured, as a guide mesh under /RegionsOfView) ; return the layer path."""
        with self.writing():
            return self._write_epoch(epoch_id, elements, provenance, region_of_view, segments)

    def _write_epoch(self, epoch_id: str, elements: Sequence[ElementSet], provenance: dict,
                     region_of_view: tuple[np.ndarray, np.ndarray] | None = None,
                     segments: Sequence[dict] = ()) -> Path:
        if not Tf.IsValidIdentifier(epoch_id):
            raise TwinStoreError(f"epoch id {epoch_id!r} is not a valid identifier")
        existing = self.epochs()
        if epoch_id in existing:
            raise TwinStoreError(f"{self._path}: epoch {epoch_id!r} is already in the twin")
        keys = [e.key for e in elements]
        if len(set(keys)) != len(keys):
            raise TwinStoreError(f"epoch {epoch_id}: duplicate element set keys")
        layer = Sdf.Layer.CreateAnonymous(f"{epoch_id}.usdc")
        stage = self._stage_upto(existing, extra=layer)
        stage.SetEditTarget(Usd.EditTarget(layer))
        twin = stage.GetPrimAtPath(TWIN_PRIM)
        known = {c.GetName(): c for c in twin.GetChildren()} if twin else {}
        if not twin:
            UsdGeom.Xform.Define(stage, TWIN_PRIM)
        missing = sorted(set(known) - set(keys))
        if missing:
            raise TwinStoreError(f"epoch {epoch_id}: element sets {missing} of earlier epochs are missing; removal is "
                                 f"expressed by state and visibility, never by dropping a set")
        for es in elements:
            if es.key in known:
                self._override(stage, known[es.key], es, epoch_id)
            else:
                self._define(stage, es)
        if region_of_view is not None:
            self._define_rov(stage, epoch_id, *region_of_view)
        for seg in segments:
            self._define_segment(stage, epoch_id, seg)
        layer.customLayerData = {"gdt": {"epoch": epoch_id, "state_names": Vt.StringArray(list(STATE_NAMES)),
                                         "reason_names": Vt.StringArray(list(REASON_NAMES)),
                                         "provenance_json": json.dumps(provenance, sort_keys=True, default=str)}}
        target = self._epoch_file(epoch_id)
        _export_atomic(layer, target)
        root = self._root()
        new_root = Sdf.Layer.CreateAnonymous("root.usda")
        new_root.TransferContent(root)
        new_root.subLayerPaths.insert(0, f"{EPOCH_DIR}/{epoch_id}.usdc")
        _export_atomic(new_root, self.root_path)
        return target

    def _define(self, stage: Usd.Stage, es: ElementSet) -> None:
        path = f"{TWIN_PRIM}/{es.key}"
        pts = np.asarray(es.points, dtype=np.float64)
        origin = (pts.min(axis=0) + pts.max(axis=0)) / 2 if len(pts) else np.zeros(3)
        local = (pts - origin).astype(np.float32)
        if es.kind == "mesh":
            geom = UsdGeom.Mesh.Define(stage, path)
            faces = np.asarray(es.faces, dtype=np.int32)
            geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
            geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
            geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            geom.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(_face_normals(local, faces).astype(np.float32)))
            geom.SetNormalsInterpolation(UsdGeom.Tokens.uniform)
            geom.CreateHoleIndicesAttr(Vt.IntArray.FromNumpy(np.flatnonzero(~np.asarray(es.visible)).astype(np.int32)))
        else:
            geom = UsdGeom.Points.Define(stage, path)
            ids = np.arange(len(pts), dtype=np.int64) if es.ids is None else np.asarray(es.ids, dtype=np.int64)
            geom.CreateIdsAttr(Vt.Int64Array.FromNumpy(ids))
            geom.CreateWidthsAttr(Vt.FloatArray.FromNumpy(_point_widths(pts, es.visible)))
            geom.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
        geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(local))
        geom.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, local.min(axis=0))),
                                             Gf.Vec3f(*map(float, local.max(axis=0)))]))
        geom.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, origin)))
        if not np.any(es.visible):
            geom.MakeInvisible()
        api = UsdGeom.PrimvarsAPI(geom.GetPrim())
        model = api.CreatePrimvar("gdt:uncertaintyModel", Sdf.ValueTypeNames.Token, UsdGeom.Tokens.constant)
        model.Set(es.uncertainty_model)
        for name, (tname, interp, arr, size, doc) in _values(es).items():
            pv = api.CreatePrimvar(name, tname, interp, size)
            pv.Set(_vt(tname, arr))
            if doc:
                pv.GetAttr().SetDocumentation(doc)

    def _override(self, stage: Usd.Stage, prim: Usd.Prim, es: ElementSet, epoch_id: str) -> None:
        geom = UsdGeom.PointBased(prim)
        kind = "mesh" if prim.IsA(UsdGeom.Mesh) else "points"
        old_local = np.asarray(geom.GetPointsAttr().Get(), dtype=np.float32)
        ops = UsdGeom.Xformable(prim).GetOrderedXformOps()
        origin = np.asarray(ops[0].Get(), dtype=np.float64) if ops else np.zeros(3)
        new_local = (np.asarray(es.points, dtype=np.float64) - origin).astype(np.float32)
        same = kind == es.kind and old_local.shape == new_local.shape and np.array_equal(old_local, new_local)
        if same and kind == "mesh":
            old_faces = np.asarray(UsdGeom.Mesh(prim).GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
            same = np.array_equal(old_faces, np.asarray(es.faces))
        if not same:
            raise TwinStoreError(f"epoch {epoch_id}: geometry of an existing element set cannot change: {es.key} "
                                 f"(changed geometry comes in as a new set)")
        api = UsdGeom.PrimvarsAPI(prim)
        old_model = api.GetPrimvar("gdt:uncertaintyModel").Get()
        if old_model != es.uncertainty_model:
            api.CreatePrimvar("gdt:uncertaintyModel", Sdf.ValueTypeNames.Token,
                              UsdGeom.Tokens.constant).Set(es.uncertainty_model)
        for name, (tname, interp, arr, size, doc) in _values(es).items():
            old = api.GetPrimvar(name)
            if old and _same(old.Get(), arr):
                continue
            pv = api.CreatePrimvar(name, tname, interp, size)  # restates type and interpolation in this layer
            pv.SetInterpolation(interp)
            if size != 1:
                pv.SetElementSize(size)
            pv.Set(_vt(tname, arr))
            if doc:
                pv.GetAttr().SetDocumentation(doc)
        if kind == "mesh":
            holes = np.flatnonzero(~np.asarray(es.visible)).astype(np.int32)
            mesh = UsdGeom.Mesh(prim)
            if not _same(mesh.GetHoleIndicesAttr().Get(), holes):
                mesh.CreateHoleIndicesAttr().Set(Vt.IntArray.FromNumpy(holes))
        else:
            points = UsdGeom.Points(prim)
            widths = _point_widths(np.asarray(es.points, dtype=np.float64), es.visible)
            if not _same(points.GetWidthsAttr().Get(), widths):
                points.CreateWidthsAttr().Set(Vt.FloatArray.FromNumpy(widths))
                points.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
        imageable = UsdGeom.Imageable(prim)
        hidden_now = imageable.GetVisibilityAttr().Get() == UsdGeom.Tokens.invisible
        if hidden_now and np.any(es.visible):
            imageable.MakeVisible()
        elif not hidden_now and not np.any(es.visible):
            imageable.MakeInvisible()

    def _define_rov(self, stage: Usd.Stage, epoch_id: str, points: np.ndarray, faces: np.ndarray) -> None:
        pts = np.asarray(points, dtype=np.float64)
        fcs = np.asarray(faces, dtype=np.int32)
        if pts.ndim != 2 or pts.shape[1:] != (3,) or fcs.ndim != 2 or fcs.shape[1:] != (3,) or \
                (fcs.size and (fcs.min() < 0 or fcs.max() >= len(pts))):
            raise TwinStoreError(f"epoch {epoch_id}: region of view must be (V,3) points and (F,3) faces into them")
        geom = UsdGeom.Mesh.Define(stage, f"{ROV_PRIM}/{epoch_id}")
        geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
        geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(fcs), 3, dtype=np.int32)))
        geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(fcs.reshape(-1)))
        geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        geom.CreatePurposeAttr(UsdGeom.Tokens.guide)  # viewers show it on request, not as twin geometry
        geom.CreateDisplayOpacityAttr(Vt.FloatArray([0.15]))
        geom.GetPrim().SetDocumentation(f"Region of view of epoch {epoch_id}: what its sensors measured")

    def _define_segment(self, stage: Usd.Stage, epoch_id: str, seg: dict) -> None:
        """One segment as a typeless prim with its figures; members as one int array per element set."""
        prim = stage.DefinePrim(f"{SEGMENTS_PRIM}/{epoch_id}/seg_{int(seg['id']):04d}")
        attrs = {"gdt:kind": (Sdf.ValueTypeNames.Token, seg["kind"]),
                 "gdt:centroid": (Sdf.ValueTypeNames.Double3, Gf.Vec3d(*map(float, seg["centroid"]))),
                 "gdt:lower": (Sdf.ValueTypeNames.Double3, Gf.Vec3d(*map(float, seg["lower"]))),
                 "gdt:upper": (Sdf.ValueTypeNames.Double3, Gf.Vec3d(*map(float, seg["upper"]))),
                 "gdt:meanScore": (Sdf.ValueTypeNames.Double, float(seg["mean_score"])),
                 "gdt:elementCount": (Sdf.ValueTypeNames.Int, int(seg["size"])),
                 "gdt:artefact": (Sdf.ValueTypeNames.Bool, bool(seg["artefact"]))}
        if seg.get("part") is not None:
            attrs.update({
                "gdt:part": (Sdf.ValueTypeNames.String, str(seg["part"])),
                "gdt:partCentre": (Sdf.ValueTypeNames.Double3, Gf.Vec3d(*map(float, seg["part_centre"]))),
                # row-major 4x4 acting on column vectors (not Gf.Matrix4d, which acts on row vectors)
                "gdt:partPose": (Sdf.ValueTypeNames.DoubleArray,
                                 Vt.DoubleArray.FromNumpy(np.asarray(seg["part_pose"], dtype=np.float64).ravel())),
                "gdt:fitRms": (Sdf.ValueTypeNames.Double, float(seg["fit_rms"])),
                "gdt:fitFitness": (Sdf.ValueTypeNames.Double, float(seg["fit_fitness"]))})
        for name, (tname, value) in attrs.items():
            prim.CreateAttribute(name, tname).Set(value)
        for key, idx in seg["members"].items():
            if not Tf.IsValidIdentifier(key):
                raise TwinStoreError(f"segment member set {key!r} is not a valid identifier")
            prim.CreateAttribute(f"gdt:members:{key}", Sdf.ValueTypeNames.Int64Array).Set(
                Vt.Int64Array.FromNumpy(np.asarray(idx, dtype=np.int64)))

    def read_segments(self, epoch_id: str) -> list[dict]:
        """The segments (connected changed elements) an epoch recorded, as dicts, in id order."""
        epochs = self.epochs()
        if epoch_id not in epochs:
            raise TwinStoreError(f"{self._path}: no epoch {epoch_id!r} (epochs: {', '.join(epochs) or 'none'})")
        stage = self._stage_upto(epochs[: epochs.index(epoch_id) + 1])
        root = stage.GetPrimAtPath(f"{SEGMENTS_PRIM}/{epoch_id}")
        out = []
        for prim in (root.GetChildren() if root else []):
            values = {a.GetName(): a.Get() for a in prim.GetAttributes()}
            get = values.get
            members = {a.GetName()[len("gdt:members:"):]: np.asarray(a.Get(), dtype=np.int64)
                       for a in prim.GetAttributes() if a.GetName().startswith("gdt:members:")}
            out.append({"id": int(prim.GetName()[4:]), "kind": str(get("gdt:kind")),
                        "centroid": np.array(get("gdt:centroid")), "lower": np.array(get("gdt:lower")),
                        "upper": np.array(get("gdt:upper")), "mean_score": float(get("gdt:meanScore")),
                        "size": int(get("gdt:elementCount")), "artefact": bool(get("gdt:artefact")),
                        "members": members})
            if get("gdt:part") is not None:
                out[-1].update({"part": str(get("gdt:part")), "part_centre": np.array(get("gdt:partCentre")),
                                "part_pose": np.asarray(get("gdt:partPose"), dtype=np.float64).reshape(4, 4),
                                "fit_rms": float(get("gdt:fitRms")), "fit_fitness": float(get("gdt:fitFitness"))})
        return sorted(out, key=lambda d: d["id"])

    def read_region_of_view(self, epoch_id: str) -> tuple[np.ndarray, np.ndarray] | None:
        """The region of view stored with ``epoch_id`` (points, faces), or None when the epoch has none."""
        epochs = self.epochs()
        if epoch_id not in epochs:
            raise TwinStoreError(f"{self._path}: no epoch {epoch_id!r} (epochs: {', '.join(epochs) or 'none'})")
        stage = self._stage_upto(epochs[: epochs.index(epoch_id) + 1])
        prim = stage.GetPrimAtPath(f"{ROV_PRIM}/{epoch_id}")
        if not prim:
            return None
        geom = UsdGeom.Mesh(prim)
        pts = np.asarray(geom.GetPointsAttr().Get(), dtype=np.float64)
        faces = np.asarray(geom.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
        return pts, faces

    def read_epoch(self, epoch_id: str) -> list[ElementSet]:
        """The composite as it was at ``epoch_id`` (only the layers up to it are composed)."""
        epochs = self.epochs()
        if epoch_id not in epochs:
            raise TwinStoreError(f"{self._path}: no epoch {epoch_id!r} (epochs: {', '.join(epochs) or 'none'})")
        stage = self._stage_upto(epochs[: epochs.index(epoch_id) + 1])
        twin = stage.GetPrimAtPath(TWIN_PRIM)
        return [self._read(child) for child in twin.GetChildren()] if twin else []

    def _read(self, prim: Usd.Prim) -> ElementSet:
        geom = UsdGeom.PointBased(prim)
        ops = UsdGeom.Xformable(prim).GetOrderedXformOps()
        origin = np.asarray(ops[0].Get(), dtype=np.float64) if ops else np.zeros(3)
        pts = np.asarray(geom.GetPointsAttr().Get(), dtype=np.float64) + origin
        api = UsdGeom.PrimvarsAPI(prim)

        def pv(name: str, dtype: Any, shape: tuple | None = None) -> np.ndarray | None:
            p = api.GetPrimvar(name)
            if not p or p.Get() is None:
                return None
            arr = np.asarray(p.Get(), dtype=dtype)
            return arr.reshape(shape) if shape else arr

        faces = None
        ids = None
        if prim.IsA(UsdGeom.Mesh):
            faces = np.asarray(UsdGeom.Mesh(prim).GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
        else:
            ids = np.asarray(UsdGeom.Points(prim).GetIdsAttr().Get(), dtype=np.int64)
        return ElementSet(
            key=prim.GetName(), kind="mesh" if faces is not None else "points", points=pts, faces=faces,
            uncertainty_model=str(api.GetPrimvar("gdt:uncertaintyModel").Get()),
            covariance=pv("gdt:covariance", np.float32, (-1, 6)), half_widths=pv("gdt:halfWidths", np.float32),
            rotation=pv("gdt:rotation", np.float32, (-1, 3, 3)), uncertainty_summary=pv("gdt:uncertainty", np.float32),
            state=pv("gdt:changeState", np.uint8), score=pv("gdt:changeScore", np.float32),
            source_epoch=pv("gdt:sourceEpoch", np.int32), visible=pv("gdt:visible", bool), ids=ids,
            p_value=pv("gdt:pValue", np.float32), reason=pv("gdt:fusionReason", np.uint8),
            reason_ratio=pv("gdt:fusionRatio", np.float32))

    def provenance(self, epoch_id: str) -> dict:
        """The provenance recorded with an epoch."""
        if epoch_id not in self.epochs():
            raise TwinStoreError(f"{self._path}: no epoch {epoch_id!r}")
        data = _open_layer(self._epoch_file(epoch_id)).customLayerData.get("gdt", {})
        return json.loads(data.get("provenance_json", "{}"))

    # ----------------------------------------------------------------------------------------------------------------
    # History queries

    def history(self) -> list[EpochRecord]:
        """One record per epoch, oldest first: when it was made, from which inputs, and its state counts."""
        out = []
        for index, eid in enumerate(self.epochs()):
            prov = self.provenance(eid)
            counts = prov.get("counts") or _count_states(self.read_epoch(eid))
            out.append(EpochRecord(id=eid, index=index, role=prov.get("epoch", {}).get("role", ""),
                                   started=prov.get("started", ""), finished=prov.get("finished", ""),
                                   inputs=prov.get("inputs", []), counts=counts, provenance=prov))
        return out

    def diff(self, epoch_a: str, epoch_b: str) -> list[SetDiff]:
        """What changed from the twin at ``epoch_a`` to the twin at ``epoch_b``, per element set."""
        epochs = self.epochs()
        for e in (epoch_a, epoch_b):
            if e not in epochs:
                raise TwinStoreError(f"{self._path}: no epoch {e!r} (epochs: {', '.join(epochs) or 'none'})")
        before = {e.key: e for e in self.read_epoch(epoch_a)}
        out = []
        for es in self.read_epoch(epoch_b):
            old = before.get(es.key)
            vis_b = np.asarray(es.visible, dtype=bool)
            vis_a = np.zeros_like(vis_b) if old is None else np.asarray(old.visible, dtype=bool)
            transitions: dict[str, int] = {}
            if old is not None:
                moved = old.state != es.state
                pairs, counts = np.unique(np.stack([old.state[moved], es.state[moved]], axis=1), axis=0,
                                          return_counts=True)
                for (a, b), c in zip(pairs.tolist(), counts.tolist(), strict=True):
                    transitions[f"{STATE_NAMES[a]}->{STATE_NAMES[b]}"] = int(c)
            visible_states = np.bincount(es.state[vis_b], minlength=len(STATE_NAMES))
            out.append(SetDiff(key=es.key, kind=es.kind, added=old is None, elements=es.n_elements,
                               came_in=int(np.sum(vis_b & ~vis_a)), went_out=int(np.sum(vis_a & ~vis_b)),
                               transitions=transitions,
                               visible=dict(zip(STATE_NAMES, map(int, visible_states), strict=True))))
        return out

    def flatten(self, epoch_id: str, out: str | Path) -> Path:
        """Write the twin as it was at ``epoch_id`` as one flat USD file, with every epoch's provenance copied in."""
        out = Path(out)
        epochs = self.epochs()
        if epoch_id not in epochs:
            raise TwinStoreError(f"{self._path}: no epoch {epoch_id!r} (epochs: {', '.join(epochs) or 'none'})")
        upto = epochs[: epochs.index(epoch_id) + 1]
        flat = self._stage_upto(upto).Flatten()
        # Flattening keeps only the root layer's metadata: carry each epoch's provenance over explicitly.
        flat.customLayerData = {"gdt": {"twin": str(self._path.resolve()), "epoch": epoch_id,
                                        "epochs": Vt.StringArray(upto),
                                        "state_names": Vt.StringArray(list(STATE_NAMES)),
                                        "reason_names": Vt.StringArray(list(REASON_NAMES)),
                                        "provenance_json": json.dumps({e: self.provenance(e) for e in upto},
                                                                      sort_keys=True, default=str)}}
        flat.defaultPrim = TWIN_PRIM.strip("/")
        out.parent.mkdir(parents=True, exist_ok=True)
        _export_atomic(flat, out)
        return out

    def export_usdz(self, epoch_id: str, out: str | Path) -> Path:
        """Package the twin at ``epoch_id`` as a .usdz (flattened, provenance included)."""
        from pxr import UsdUtils

        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory() as tmp:
            asset = self.flatten(epoch_id, Path(tmp) / f"{self._path.name}_{epoch_id}.usdc")
            partial = out.with_name(f".{out.stem}.tmp-{os.getpid()}.usdz")
            if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(asset)), str(partial)):
                raise TwinStoreError(f"could not write {out}")
            os.replace(partial, out)
        return out


@dataclass(frozen=True)
class EpochRecord:
    """One epoch of a twin's history."""

    id: str
    index: int
    role: str
    started: str
    finished: str
    inputs: list = field(default_factory=list)
    counts: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SetDiff:
    """How one element set changed between two epochs."""

    key: str
    kind: str
    added: bool
    elements: int
    came_in: int
    went_out: int
    transitions: dict = field(default_factory=dict)
    visible: dict = field(default_factory=dict)


def _count_states(elements: Sequence[ElementSet]) -> dict[str, int]:
    total = np.zeros(len(STATE_NAMES), dtype=np.int64)
    for es in elements:
        total += np.bincount(es.state[np.asarray(es.visible, dtype=bool)], minlength=len(STATE_NAMES))
    return dict(zip(STATE_NAMES, map(int, total), strict=True))
