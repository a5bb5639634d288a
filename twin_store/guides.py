"""What an epoch records beside its element sets: the region of view its sensors measured (a guide mesh under
``/RegionsOfView``) and its segments, the connected changed elements (typeless prims under ``/Segments``)."""

from __future__ import annotations

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

from .errors import TwinStoreError
from .names import ROV_PRIM, SEGMENTS_PRIM
from .segments import Segment

MEMBERS = "gdt:members:"  # namespace of a segment's member indices, one int array per element set


def define_region_of_view(stage: Usd.Stage, epoch_id: str, points: np.ndarray, faces: np.ndarray) -> None:
    """Author an epoch's region of view as a guide mesh ``/RegionsOfView/<epoch>``."""
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


def read_region_of_view(stage: Usd.Stage, epoch_id: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The region of view an epoch recorded (points, faces), or None when it has none."""
    prim = stage.GetPrimAtPath(f"{ROV_PRIM}/{epoch_id}")
    if not prim:
        return None
    geom = UsdGeom.Mesh(prim)
    pts = np.asarray(geom.GetPointsAttr().Get(), dtype=np.float64)
    faces = np.asarray(geom.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
    return pts, faces


def define_segment(stage: Usd.Stage, epoch_id: str, seg: Segment) -> None:
    """One segment as a typeless prim with its figures; members as one int array per element set."""
    prim = stage.DefinePrim(f"{SEGMENTS_PRIM}/{epoch_id}/seg_{int(seg.id):04d}")
    attrs = {"gdt:kind": (Sdf.ValueTypeNames.Token, seg.kind),
             "gdt:centroid": (Sdf.ValueTypeNames.Double3, Gf.Vec3d(*map(float, seg.centroid))),
             "gdt:lower": (Sdf.ValueTypeNames.Double3, Gf.Vec3d(*map(float, seg.lower))),
             "gdt:upper": (Sdf.ValueTypeNames.Double3, Gf.Vec3d(*map(float, seg.upper))),
             "gdt:meanScore": (Sdf.ValueTypeNames.Double, float(seg.mean_score)),
             "gdt:elementCount": (Sdf.ValueTypeNames.Int, int(seg.size)),
             "gdt:artefact": (Sdf.ValueTypeNames.Bool, bool(seg.artefact))}
    if seg.part is not None:
        attrs.update({
            "gdt:part": (Sdf.ValueTypeNames.String, str(seg.part)),
            "gdt:partCentre": (Sdf.ValueTypeNames.Double3, Gf.Vec3d(*map(float, _given(seg.part_centre)))),
            # row-major 4x4 acting on column vectors (not Gf.Matrix4d, which acts on row vectors)
            "gdt:partPose": (Sdf.ValueTypeNames.DoubleArray,
                             Vt.DoubleArray.FromNumpy(np.asarray(seg.part_pose, dtype=np.float64).ravel())),
            "gdt:fitRms": (Sdf.ValueTypeNames.Double, float(seg.fit_rms)),
            "gdt:fitFitness": (Sdf.ValueTypeNames.Double, float(seg.fit_fitness))})
    if seg.moved_from is not None:
        attrs.update({
            "gdt:movedFrom": (Sdf.ValueTypeNames.Int, int(seg.moved_from)),
            "gdt:movedItem": (Sdf.ValueTypeNames.String, str(seg.moved_item)),
            "gdt:displacement": (Sdf.ValueTypeNames.Double3, Gf.Vec3d(*map(float, _given(seg.displacement)))),
            "gdt:rotationDeg": (Sdf.ValueTypeNames.Double, float(seg.rotation_deg))})
    for name, (tname, value) in attrs.items():
        prim.CreateAttribute(name, tname).Set(value)
    for key, idx in seg.members.items():
        if not Tf.IsValidIdentifier(key):
            raise TwinStoreError(f"segment member set {key!r} is not a valid identifier")
        prim.CreateAttribute(f"{MEMBERS}{key}", Sdf.ValueTypeNames.Int64Array).Set(
            Vt.Int64Array.FromNumpy(np.asarray(idx, dtype=np.int64)))


def _given(values: np.ndarray | None) -> np.ndarray:
    if values is None:
        raise TwinStoreError("a segment with a fitted part or a move needs its centre and displacement")
    return values


def read_segments(stage: Usd.Stage, epoch_id: str, *, members: bool = True) -> list[Segment]:
    """The segments an epoch recorded, in id order (``members=False``: without the member indices)."""
    root = stage.GetPrimAtPath(f"{SEGMENTS_PRIM}/{epoch_id}")
    out = [_read_segment(prim, members) for prim in (root.GetChildren() if root else [])]
    return sorted(out, key=lambda g: g.id)


def _read_segment(prim: Usd.Prim, with_members: bool = True) -> Segment:
    """One segment prim as the ``Segment`` it was written from (members empty unless ``with_members``)."""
    values = {a.GetName(): a.Get() for a in prim.GetAttributes() if not a.GetName().startswith(MEMBERS)}
    get = values.get
    members = {a.GetName()[len(MEMBERS):]: np.asarray(a.Get(), dtype=np.int64)
               for a in prim.GetAttributes() if with_members and a.GetName().startswith(MEMBERS)}
    part = {}
    if get("gdt:part") is not None:
        part = {"part": str(get("gdt:part")), "part_centre": np.array(get("gdt:partCentre")),
                "part_pose": np.asarray(get("gdt:partPose"), dtype=np.float64).reshape(4, 4),
                "fit_rms": float(get("gdt:fitRms")), "fit_fitness": float(get("gdt:fitFitness"))}
    moved = {}
    if get("gdt:movedFrom") is not None:
        moved = {"moved_from": int(get("gdt:movedFrom")), "moved_item": str(get("gdt:movedItem")),
                 "displacement": np.array(get("gdt:displacement")), "rotation_deg": float(get("gdt:rotationDeg"))}
    kind = str(get("gdt:kind"))
    if kind not in ("new", "removed"):
        raise TwinStoreError(f"segment {prim.GetPath()}: kind {kind!r} is neither 'new' nor 'removed'")
    return Segment(id=int(prim.GetName()[4:]), kind="new" if kind == "new" else "removed",
                   centroid=np.array(get("gdt:centroid")), lower=np.array(get("gdt:lower")),
                   upper=np.array(get("gdt:upper")), mean_score=float(get("gdt:meanScore")),
                   size=int(get("gdt:elementCount")), artefact=bool(get("gdt:artefact")), members=members, **part,
                   **moved)
