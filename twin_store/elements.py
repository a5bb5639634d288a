"""An element set (one dataset of the twin) and how it is written to, overridden in, and read from a USD prim.

Points are stored as float32 relative to an ``xformOp:translate`` (double) at the set's centre, so georeferenced
coordinates (UTM metres) keep their precision. Per-element values are primvars in the ``gdt:`` namespace with
interpolation ``vertex`` (points) or ``uniform`` (facets), restated in every layer that writes them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

from . import names
from .errors import TwinStoreError
from .names import TWIN_PRIM, state_colours

DOC_DOF = ("Student t degrees of freedom per element of a heavy-tailed gaussian uncertainty (a Gaussian scale "
           "mixture); gdt:covariance then holds the t's scale matrix, not its covariance.")
# name -> (value type, interpolation, array, element size, documentation)
Primvars = dict[str, tuple[Any, Any, np.ndarray, int, str | None]]
# where a part of a larger set stands: the set's origin (its points are relative to it) and its diagonal (widths)
Frame = tuple[np.ndarray, float]
# the optional and per-element fields besides the geometry, and the shape of one element's value
ROW_SHAPES: dict[str, tuple[int, ...]] = {
    "uncertainty_summary": (), "state": (), "score": (), "source_epoch": (), "visible": (), "covariance": (6,),
    "half_widths": (3,), "rotation": (3, 3), "ids": (), "display_color": (3,), "p_value": (), "reason": (),
    "reason_ratio": (), "area_seen": (), "area_removed": (), "intensity": (), "scan_color": (3,), "dof": (),
    "classification": ()}
# the fields holding one value (or row) per element of a point set
PER_ELEMENT = ("points", *ROW_SHAPES)


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
    area_seen: np.ndarray | None = None  # (E,) share of the element's area a station saw, NaN where not judged
    area_removed: np.ndarray | None = None  # (E,) share of the element's area seen through (removed)
    intensity: np.ndarray | None = None  # (E,) return intensity from the scan file
    scan_color: np.ndarray | None = None  # (E,3) colour from the scan file, 0..1
    identity: dict[str, str] | None = None  # who the set is outside the twin (IFC GlobalId and class, part name)
    dof: np.ndarray | None = None  # (E,) Student t degrees of freedom of a heavy-tailed gaussian (covariance: scale)
    classification: np.ndarray | None = None  # (E,) uint8 ASPRS class from a LAS/LAZ file
    item: dict[str, str] | None = None  # what brought the set in: {"epoch", "role", "name"} of the dataset

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
        for name, row in ROW_SHAPES.items():
            shape = (n, *row)
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


def face_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normal per triangle (zero for degenerate ones)."""
    tri = points[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def display_colours(es: ElementSet) -> np.ndarray:
    """What a viewer shows per element: the set's display colour where it has one, else the change state's."""
    return state_colours(es.state) if es.display_color is None else np.asarray(es.display_color)


def primvar_values(es: ElementSet) -> Primvars:
    """Per-element primvars of a set: name -> (value type, interpolation, array, element size, documentation)."""
    types = Sdf.ValueTypeNames
    interp = UsdGeom.Tokens.uniform if es.kind == "mesh" else UsdGeom.Tokens.vertex
    state = np.asarray(es.state, dtype=np.uint8)
    colour = display_colours(es).astype(np.float32)
    out: Primvars = {
        "gdt:uncertainty": (types.FloatArray, interp, np.asarray(es.uncertainty_summary, dtype=np.float32), 1,
                            names.DOC_UNCERTAINTY),
        "gdt:changeScore": (types.FloatArray, interp, np.asarray(es.score, dtype=np.float32), 1, names.DOC_SCORE),
        "gdt:changeState": (types.UCharArray, interp, state, 1, names.DOC_STATE),
        "gdt:sourceEpoch": (types.IntArray, interp, np.asarray(es.source_epoch, dtype=np.int32), 1,
                            names.DOC_SOURCE_EPOCH),
        "gdt:visible": (types.BoolArray, interp, np.asarray(es.visible, dtype=bool), 1, names.DOC_VISIBLE),
        "displayColor": (types.Color3fArray, interp, colour, 1, None),
    }
    # the optional values, in the order they are authored
    if es.covariance is not None:
        out["gdt:covariance"] = (types.FloatArray, interp, np.asarray(es.covariance, dtype=np.float32).reshape(-1),
                                 6, names.DOC_COVARIANCE)
    if es.half_widths is not None:
        out["gdt:halfWidths"] = (types.Float3Array, interp, np.asarray(es.half_widths, np.float32), 1,
                                 names.DOC_HALF_WIDTHS)
    if es.p_value is not None:
        out["gdt:pValue"] = (types.FloatArray, interp, np.asarray(es.p_value, dtype=np.float32), 1, names.DOC_P_VALUE)
    if es.reason is not None:
        out["gdt:fusionReason"] = (types.UCharArray, interp, np.asarray(es.reason, dtype=np.uint8), 1,
                                   names.DOC_REASON)
    if es.reason_ratio is not None:
        out["gdt:fusionRatio"] = (types.FloatArray, interp, np.asarray(es.reason_ratio, dtype=np.float32), 1,
                                  names.DOC_RATIO)
    for attr, name, doc in (("area_seen", "gdt:areaSeen", names.DOC_AREA_SEEN),
                            ("area_removed", "gdt:areaRemoved", names.DOC_AREA_REMOVED)):
        if getattr(es, attr) is not None:
            out[name] = (types.FloatArray, interp, np.asarray(getattr(es, attr), dtype=np.float32), 1, doc)
    if es.intensity is not None:
        out["gdt:intensity"] = (types.FloatArray, interp, np.asarray(es.intensity, np.float32), 1, names.DOC_INTENSITY)
    if es.scan_color is not None:
        out["gdt:scanColor"] = (types.Color3fArray, interp, np.asarray(es.scan_color, np.float32), 1,
                                names.DOC_SCAN_COLOR)
    if es.classification is not None:
        out["gdt:classification"] = (types.UCharArray, interp, np.asarray(es.classification, np.uint8), 1,
                                     names.DOC_CLASSIFICATION)
    if es.dof is not None:
        out["gdt:studentDof"] = (types.FloatArray, interp, np.asarray(es.dof, np.float32), 1, DOC_DOF)
    if es.rotation is not None:
        out["gdt:rotation"] = (types.FloatArray, interp, np.asarray(es.rotation, dtype=np.float32).reshape(-1), 9,
                               names.DOC_ROTATION)
    return out


def diagonal(points: np.ndarray) -> float:
    """The length of a point set's bounding-box diagonal (0 for no points)."""
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) if len(points) else 0.0


def point_widths(points: np.ndarray, visible: np.ndarray, diag: float | None = None) -> np.ndarray:
    """Per-point widths: 1/500 of the set's diagonal (``diag``, else that of ``points``), and 0 for hidden points,
    so that plain viewers hide them."""
    diag = diagonal(points) if diag is None else diag
    return np.where(np.asarray(visible, dtype=bool), diag / 500.0 if diag > 0 else 0.002, 0.0).astype(np.float32)


def vt_array(type_name: Any, arr: np.ndarray) -> Any:
    """A numpy array as the Vt array of a USD value type."""
    if type_name == Sdf.ValueTypeNames.BoolArray:
        return Vt.BoolArray([bool(v) for v in arr]) if arr.size < 64 else Vt.BoolArray.FromNumpy(arr)
    return type_name.type.pythonClass.FromNumpy(np.ascontiguousarray(arr))


def same_values(old: Any, new: np.ndarray) -> bool:
    """Whether a stored value already equals ``new`` (NaNs equal), so a later layer need not restate it."""
    if old is None:
        return False
    a = np.asarray(old)
    if a.shape != new.shape and a.size == new.size:
        a = a.reshape(new.shape)
    return a.shape == new.shape and bool(np.array_equal(a, new, equal_nan=a.dtype.kind == "f"))


def set_frame(points: np.ndarray) -> Frame:
    """A set's origin (the centre of its bounding box, where its float32 points are relative to) and diagonal."""
    pts = np.asarray(points, dtype=np.float64)
    origin = (pts.min(axis=0) + pts.max(axis=0)) / 2 if len(pts) else np.zeros(3)
    return origin, diagonal(pts)


def define_element_set(stage: Usd.Stage, es: ElementSet, path: str | None = None, frame: Frame | None = None
                       ) -> None:
    """Author a new set as ``/Twin/<key>`` (or ``path``) on the stage's edit target: geometry, translate, primvars.

    With a ``frame`` the set is a part of a larger one (``parts``): its points are relative to the larger set's
    origin, it has no translate of its own (its parent has), and its widths follow the larger set's diagonal."""
    path = f"{TWIN_PRIM}/{es.key}" if path is None else path
    pts = np.asarray(es.points, dtype=np.float64)
    origin, diag = set_frame(pts) if frame is None else frame
    local = (pts - origin).astype(np.float32)
    if es.kind == "mesh":
        geom = UsdGeom.Mesh.Define(stage, path)
        faces = np.asarray(es.faces, dtype=np.int32)
        geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
        geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
        geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        geom.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(face_normals(local, faces).astype(np.float32)))
        geom.SetNormalsInterpolation(UsdGeom.Tokens.uniform)
        geom.CreateHoleIndicesAttr(Vt.IntArray.FromNumpy(np.flatnonzero(~np.asarray(es.visible)).astype(np.int32)))
    else:
        geom = UsdGeom.Points.Define(stage, path)
        ids = np.arange(len(pts), dtype=np.int64) if es.ids is None else np.asarray(es.ids, dtype=np.int64)
        geom.CreateIdsAttr(Vt.Int64Array.FromNumpy(ids))
        geom.CreateWidthsAttr(Vt.FloatArray.FromNumpy(point_widths(pts, es.visible, diag)))
        geom.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(local))
    geom.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, local.min(axis=0))),
                                         Gf.Vec3f(*map(float, local.max(axis=0)))]))
    if frame is None:
        geom.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, origin)))
    if not np.any(es.visible):
        geom.MakeInvisible()
    if es.identity:
        geom.GetPrim().SetCustomDataByKey(names.IDENTITY_KEY, {str(k): str(v) for k, v in es.identity.items()})
    if es.item:
        geom.GetPrim().SetCustomDataByKey(names.ITEM_KEY, {str(k): str(v) for k, v in es.item.items()})
    api = UsdGeom.PrimvarsAPI(geom.GetPrim())
    model = api.CreatePrimvar("gdt:uncertaintyModel", Sdf.ValueTypeNames.Token, UsdGeom.Tokens.constant)
    model.Set(es.uncertainty_model)
    for name, (tname, interp, arr, size, doc) in primvar_values(es).items():
        pv = api.CreatePrimvar(name, tname, interp, size)
        pv.Set(vt_array(tname, arr))
        if doc:
            pv.GetAttr().SetDocumentation(doc)


def override_element_set(prim: Usd.Prim, es: ElementSet, epoch_id: str, frame: Frame | None = None) -> None:
    """Author, on the stage's edit target, the per-element values of a known set that differ from what is stored
    (a part of a larger set with its ``frame``, as in ``define_element_set``).

    The geometry of a known set never changes (changed geometry comes in as a new set)."""
    origin = set_origin(prim) if frame is None else frame[0]
    kind = _check_same_geometry(prim, es, epoch_id, origin)
    _restate_primvars(UsdGeom.PrimvarsAPI(prim), es)
    _restate_visibility(prim, kind, es, None if frame is None else frame[1])


def _check_same_geometry(prim: Usd.Prim, es: ElementSet, epoch_id: str, origin: np.ndarray) -> str:
    """The stored set's kind, after checking its points (and faces) are those of ``es``."""
    geom = UsdGeom.PointBased(prim)
    kind = "mesh" if prim.IsA(UsdGeom.Mesh) else "points"
    old_local = np.asarray(geom.GetPointsAttr().Get(), dtype=np.float32)
    new_local = (np.asarray(es.points, dtype=np.float64) - origin).astype(np.float32)
    same = kind == es.kind and old_local.shape == new_local.shape and np.array_equal(old_local, new_local)
    if same and kind == "mesh":
        old_faces = np.asarray(UsdGeom.Mesh(prim).GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        same = np.array_equal(old_faces, np.asarray(es.faces))
    if not same:
        raise TwinStoreError(f"epoch {epoch_id}: geometry of an existing element set cannot change: {es.key} "
                             f"(changed geometry comes in as a new set)")
    return kind


def _restate_primvars(api: UsdGeom.PrimvarsAPI, es: ElementSet) -> None:
    """Author the uncertainty model and every primvar whose value differs from the composed one."""
    old_model = api.GetPrimvar("gdt:uncertaintyModel").Get()
    if old_model != es.uncertainty_model:
        api.CreatePrimvar("gdt:uncertaintyModel", Sdf.ValueTypeNames.Token,
                          UsdGeom.Tokens.constant).Set(es.uncertainty_model)
    for name, (tname, interp, arr, size, doc) in primvar_values(es).items():
        old = api.GetPrimvar(name)
        if old and same_values(old.Get(), arr):
            continue
        pv = api.CreatePrimvar(name, tname, interp, size)  # restates type and interpolation in this layer
        pv.SetInterpolation(interp)
        if size != 1:
            pv.SetElementSize(size)
        pv.Set(vt_array(tname, arr))
        if doc:
            pv.GetAttr().SetDocumentation(doc)


def _restate_visibility(prim: Usd.Prim, kind: str, es: ElementSet, diag: float | None) -> None:
    """Author what plain viewers use to hide elements (mesh holes, zero point widths) and the set's visibility."""
    if kind == "mesh":
        holes = np.flatnonzero(~np.asarray(es.visible)).astype(np.int32)
        mesh = UsdGeom.Mesh(prim)
        if not same_values(mesh.GetHoleIndicesAttr().Get(), holes):
            mesh.CreateHoleIndicesAttr().Set(Vt.IntArray.FromNumpy(holes))
    else:
        points = UsdGeom.Points(prim)
        widths = point_widths(np.asarray(es.points, dtype=np.float64), es.visible, diag)
        if not same_values(points.GetWidthsAttr().Get(), widths):
            points.CreateWidthsAttr().Set(Vt.FloatArray.FromNumpy(widths))
            points.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    restate_prim_visibility(prim, bool(np.any(es.visible)))


def restate_prim_visibility(prim: Usd.Prim, any_visible: bool) -> None:
    """Hide a prim whose elements are all hidden (and show it again if one is visible), where that changed."""
    imageable = UsdGeom.Imageable(prim)
    hidden_now = imageable.GetVisibilityAttr().Get() == UsdGeom.Tokens.invisible
    if hidden_now and any_visible:
        imageable.MakeVisible()
    elif not hidden_now and not any_visible:
        imageable.MakeInvisible()


def set_origin(prim: Usd.Prim) -> np.ndarray:
    """The world position a set's float32 points are relative to (its translate op; zero without one)."""
    ops = UsdGeom.Xformable(prim).GetOrderedXformOps()
    return np.asarray(ops[0].Get(), dtype=np.float64) if ops else np.zeros(3)


# field -> (primvar, dtype) of the per-element values a set is read back with
READ_PRIMVARS: dict[str, tuple[str, Any]] = {
    "covariance": ("gdt:covariance", np.float32), "half_widths": ("gdt:halfWidths", np.float32),
    "rotation": ("gdt:rotation", np.float32), "uncertainty_summary": ("gdt:uncertainty", np.float32),
    "state": ("gdt:changeState", np.uint8), "score": ("gdt:changeScore", np.float32),
    "source_epoch": ("gdt:sourceEpoch", np.int32), "visible": ("gdt:visible", np.bool_),
    "p_value": ("gdt:pValue", np.float32), "reason": ("gdt:fusionReason", np.uint8),
    "reason_ratio": ("gdt:fusionRatio", np.float32), "area_seen": ("gdt:areaSeen", np.float32),
    "area_removed": ("gdt:areaRemoved", np.float32), "intensity": ("gdt:intensity", np.float32),
    "scan_color": ("gdt:scanColor", np.float32), "dof": ("gdt:studentDof", np.float32),
    "classification": ("gdt:classification", np.uint8),
}


def primvar_array(prim: Usd.Prim, field: str) -> np.ndarray | None:
    """One per-element value of a prim (a field of ``READ_PRIMVARS``) as its numpy array, None where it has none."""
    name, dtype = READ_PRIMVARS[field]
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(name)
    value = pv.Get() if pv else None  # read once: a large array is decoded on every Get
    return None if value is None else np.asarray(value, dtype=dtype).reshape(-1, *ROW_SHAPES[field])


def read_element_set(prim: Usd.Prim, origin: np.ndarray | None = None) -> ElementSet:
    """The element set a composed ``/Twin/<key>`` prim holds, in world coordinates (a part's relative to the
    ``origin`` of its set)."""
    geom = UsdGeom.PointBased(prim)
    origin = set_origin(prim) if origin is None else origin
    pts = np.asarray(geom.GetPointsAttr().Get(), dtype=np.float64) + origin
    faces = None
    ids = None
    if prim.IsA(UsdGeom.Mesh):
        faces = np.asarray(UsdGeom.Mesh(prim).GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
    else:
        ids = np.asarray(UsdGeom.Points(prim).GetIdsAttr().Get(), dtype=np.int64)
    return ElementSet(
        key=prim.GetName(), kind="mesh" if faces is not None else "points", points=pts, faces=faces,
        uncertainty_model=uncertainty_model_of(prim), ids=ids, identity=identity_of(prim), item=item_of(prim),
        **{field: primvar_array(prim, field) for field in READ_PRIMVARS})


def uncertainty_model_of(prim: Usd.Prim) -> str:
    """The uncertainty model a set's (or part's) prim records."""
    return str(UsdGeom.PrimvarsAPI(prim).GetPrimvar("gdt:uncertaintyModel").Get())


def identity_of(prim: Usd.Prim) -> dict[str, str] | None:
    """A set's identity outside the twin (customData ``gdt:identity``), None when it has none."""
    return _custom(prim, names.IDENTITY_KEY)


def item_of(prim: Usd.Prim) -> dict[str, str] | None:
    """What brought a set in (customData ``gdt:item``: epoch, role, dataset name), None when it has no record."""
    return _custom(prim, names.ITEM_KEY)


def _custom(prim: Usd.Prim, key: str) -> dict[str, str] | None:
    """A string dictionary the prim keeps in its customData under ``key``, None when it has none."""
    value = prim.GetCustomDataByKey(key)
    return {str(k): str(v) for k, v in value.items()} if value else None
