"""Large point sets in a layer of their own, loaded on demand, with a light preview a viewer can show instead.

A set of more than ``PAYLOAD_ELEMENTS`` points is authored in parts (``parts``): ``/Twin/<key>`` is an Xform in the
epoch layer, and each part ``/Twin/<key>/part_NNNN`` (``PART_ELEMENTS`` consecutive rows) is authored in
``epochs/<epoch>.<key>.part_NNNN.usdc``, to which the epoch layer gives the part a payload arc; one part's arrays are
built at a time. Composed normally (as every reader of the twin does) the set is all there; later epochs override
the per-element values of the parts that changed in their own layers (their opinions are stronger than a payload's).
A viewer that opens the twin with payloads unloaded (``usdview --unloaded``, or
``Usd.Stage.Open(root, Usd.Stage.LoadNone)``) reads none of those points and shows ``/Previews/<key>`` instead: every
k-th point (at most ``PREVIEW_POINTS``) coloured by its change state, restated by each epoch whose states changed.
The payload file's sha256 is recorded in the root beside the epoch layers' and checked the same way.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from . import parts
from .elements import define_element_set, point_widths, same_values, set_frame
from .layers import export_atomic
from .names import IDENTITY_KEY, ITEM_KEY, TWIN_PRIM, state_colours
from .set_source import SetLike

PAYLOAD_ELEMENTS = 2_000_000
PREVIEW_POINTS = 200_000
PREVIEWS_PRIM = "/Previews"


def payload_file(epoch_id: str, key: str, part: str) -> str:
    """The file name of a set's part's payload layer (epoch ids, set keys and part names are identifiers: no dots)."""
    return f"{epoch_id}.{key}.{part}.usdc"


def wants_payload(es: SetLike, limit: int | None = None) -> bool:
    """Whether a new set goes into its own payload layer."""
    return es.kind == "points" and len(es.points) > (PAYLOAD_ELEMENTS if limit is None else limit)


def define_payload_set(stage: Usd.Stage, es: SetLike, folder: Path, epoch_id: str) -> list[tuple[str, str]]:
    """Author ``es`` in parts, each in its own layer file in ``folder`` with a payload arc to it, and its preview,
    on ``stage``'s edit target; return the files' names and sha256s."""
    path = f"{TWIN_PRIM}/{es.key}"
    origin, diag = set_frame(es.points)
    xform = UsdGeom.Xform.Define(stage, path)
    xform.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, origin)))
    size = parts.PART_ELEMENTS
    prim = xform.GetPrim()
    prim.SetCustomDataByKey(parts.PARTS_KEY, {"elements": es.n_elements, "part_elements": size})
    for key, value in ((IDENTITY_KEY, es.identity), (ITEM_KEY, es.item)):
        if value:
            prim.SetCustomDataByKey(key, {str(k): str(v) for k, v in value.items()})
    if not np.any(es.visible):
        xform.MakeInvisible()
    written = []
    for index, (start, stop) in enumerate(parts.part_ranges(es.n_elements, size)):
        part_path = f"{path}/{parts.part_name(index)}"
        layer = Sdf.Layer.CreateAnonymous(".usdc")
        define_element_set(Usd.Stage.Open(layer), parts.rows_of(es, start, stop), part_path, (origin, diag))
        target = folder / payload_file(epoch_id, es.key, parts.part_name(index))
        written.append((target.name, export_atomic(layer, target, ("payload-exported", "payload-renamed"))))
        del layer  # its arrays go now, before the next part's are built
        # absolute while the epoch layer is anonymous (so it composes now); made relative before it is written
        stage.DefinePrim(part_path).GetPayloads().AddPayload(str(target), Sdf.Path(part_path))
    define_preview(stage, es)
    return written


def relative_payloads(layer: Sdf.Layer, folder: Path) -> None:
    """Point the layer's payload arcs into ``folder`` by relative paths, so the twin can move (staging, copies)."""
    twin = layer.GetPrimAtPath(Sdf.Path(TWIN_PRIM))
    if twin is None:
        return
    for spec in [*twin.nameChildren, *(part for child in twin.nameChildren for part in child.nameChildren)]:
        items = list(spec.payloadList.prependedItems)
        if not items:
            continue
        fixed = [Sdf.Payload(f"./{Path(p.assetPath).name}" if Path(p.assetPath).parent == folder else p.assetPath,
                             p.primPath) for p in items]
        spec.payloadList.prependedItems = fixed


def preview_rows(n: int) -> np.ndarray:
    """The rows of a set of ``n`` points its preview holds: every k-th, at most ``PREVIEW_POINTS``."""
    return np.arange(0, n, max(1, -(-n // PREVIEW_POINTS)))


def _colours(es: SetLike, rows: np.ndarray) -> np.ndarray:
    return state_colours(np.asarray(es.state)[rows]).astype(np.float32)


def define_preview(stage: Usd.Stage, es: SetLike) -> None:
    """``/Previews/<key>``: every k-th point of the set, coloured by state, hidden ones zero-wide."""
    rows = preview_rows(len(es.points))
    pts = np.asarray(es.points, dtype=np.float64)[rows]
    origin = (pts.min(axis=0) + pts.max(axis=0)) / 2 if len(pts) else np.zeros(3)
    geom = UsdGeom.Points.Define(stage, f"{PREVIEWS_PRIM}/{es.key}")
    geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy((pts - origin).astype(np.float32)))
    geom.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, origin)))
    geom.CreateWidthsAttr(Vt.FloatArray.FromNumpy(point_widths(pts, np.asarray(es.visible)[rows])))
    geom.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    geom.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(Vt.Vec3fArray.FromNumpy(_colours(es, rows)))
    geom.GetPrim().SetDocumentation(f"every {max(1, -(-len(es.points) // PREVIEW_POINTS))}-th point of "
                                    f"{TWIN_PRIM}/{es.key}, for viewers that leave payloads unloaded")


def restate_preview(stage: Usd.Stage, es: SetLike) -> None:
    """A later epoch's states and visibility on the set's preview, where they changed."""
    prim = stage.GetPrimAtPath(f"{PREVIEWS_PRIM}/{es.key}")
    if not prim:
        return
    geom = UsdGeom.Points(prim)
    rows = preview_rows(len(es.points))
    colours = _colours(es, rows)
    if not same_values(geom.GetDisplayColorPrimvar().Get(), colours):
        geom.GetDisplayColorPrimvar().Set(Vt.Vec3fArray.FromNumpy(colours))
    widths = point_widths(np.asarray(es.points, dtype=np.float64)[rows], np.asarray(es.visible)[rows])
    if not same_values(geom.GetWidthsAttr().Get(), widths):
        geom.GetWidthsAttr().Set(Vt.FloatArray.FromNumpy(widths))
