"""The file-based twin: a USD root stage with one sublayer per epoch, written atomically.

Layout::

    twin/
      twin.usda        root: subLayers strongest first (epochs/E1.usdc, epochs/E0.usdc), metersPerUnit, upAxis
      epochs/E0.usdc   only the opinions of epoch E0
      epochs/E1.usdc   only the opinions of epoch E1: new prims, and overrides of earlier prims' per-element values

Each element set is one prim ``/Twin/<key>`` (UsdGeom.Mesh or UsdGeom.Points); see ``elements`` for how its
values are stored.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom, Vt

from . import guides
from .branch import branch
from .elements import ElementSet, define_element_set, identity_of, override_element_set
from .errors import TwinStoreError
from .history import EpochEntry, SetDiff, count_states, set_diff
from .integrity import LayerDigests, run_lock_problems
from .layers import export_atomic, open_layer, usd_message
from .lean import LeanSet, iter_lean_sets
from .lock import writer_lock
from .names import EPOCH_DIR, REASON_NAMES, ROOT_NAME, STATE_NAMES, TWIN_PRIM
from .parts import is_parted, override_parted_set, read_set, set_values
from .payloads import define_payload_set, relative_payloads, restate_preview, wants_payload
from .segments import Segment
from .set_source import SetLike, set_keys, whole
from .swap import leftover_advice, leftovers


class TwinStore:
    """A twin folder: create or open it, write an epoch, read the composite at any epoch and its provenance."""

    def __init__(self, path: Path, *, lock: bool = True) -> None:
        self._path = path
        self._lock = lock
        self._holding = False
        self._digests = LayerDigests()

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
        export_atomic(root, path / ROOT_NAME)
        return cls(path, lock=lock)

    @classmethod
    def open(cls, path: str | Path) -> TwinStore:
        """Open an existing twin folder."""
        path = Path(path)
        if not (path / ROOT_NAME).is_file():
            advice = "; ".join(leftover_advice(lo, path) for lo in leftovers(path.absolute()))
            raise TwinStoreError(f"{path} is not a twin (no {ROOT_NAME})" + (f"; {advice}" if advice else ""))
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
        return open_layer(self.root_path)

    def meters_per_unit(self) -> float:
        """Metres per twin unit (the root's ``metersPerUnit``)."""
        root = self._root()
        return float(root.pseudoRoot.GetInfo("metersPerUnit")) if root.pseudoRoot.HasInfo("metersPerUnit") else 1.0

    def layer_digests(self) -> dict[str, str]:
        """The sha256 of each epoch layer as recorded in the root when it was written, by sublayer path."""
        data = self._root().customLayerData.get("gdt", {})
        sums = data.get("layer_sha256", {}) if isinstance(data, dict) else None
        if not isinstance(sums, dict):
            raise TwinStoreError(f"{self.root_path}: its record of layer sha256s is not a mapping; the root is damaged")
        return {str(k): str(v) for k, v in sums.items()}

    def run_lock_problems(self) -> list[str]:
        """What is wrong with the run record ``gdt.lock`` (missing, unparsable, disagreeing sha256s); [] if fine."""
        return run_lock_problems(self._path, self.layer_digests())

    def verify(self) -> None:
        """Check every epoch layer against its recorded sha256 (a TwinStoreError names the first bad one)."""
        for eid in self.epochs():
            self._layer(eid)

    def _layer(self, epoch_id: str) -> Sdf.Layer:
        """An epoch's layer, after checking the file has the sha256 recorded when it was written."""
        path = self._epoch_file(epoch_id)
        digests = self.layer_digests()
        self._digests.verify(path, digests.get(f"{EPOCH_DIR}/{path.name}"), epoch_id)
        for rel, digest in digests.items():  # the epoch's payload layers (large point sets), checked alike
            if rel.startswith(f"{EPOCH_DIR}/{epoch_id}.") and rel != f"{EPOCH_DIR}/{path.name}":
                self._digests.verify(self._path / rel, digest, epoch_id)
        return open_layer(path)

    def epochs(self) -> list[str]:
        """Epoch ids, oldest first."""
        root = self._root()  # keep the layer alive while its list proxy is read
        return [Path(p).stem for p in reversed(list(root.subLayerPaths))]

    def _epoch_file(self, epoch_id: str) -> Path:
        return self._path / EPOCH_DIR / f"{epoch_id}.usdc"

    def _epochs_upto(self, epoch_id: str) -> list[str]:
        """The epochs up to and including ``epoch_id``, oldest first (an error naming the epochs if it is none)."""
        epochs = self.epochs()
        if epoch_id not in epochs:
            raise TwinStoreError(f"{self._path}: no epoch {epoch_id!r} (epochs: {', '.join(epochs) or 'none'})")
        return epochs[: epochs.index(epoch_id) + 1]

    def _stage_upto(self, epochs: Sequence[str], extra: Sdf.Layer | None = None) -> Usd.Stage:
        """A stage over an in-memory root holding the given epochs' layers (and an extra strongest layer)."""
        root = self._root()
        anon = Sdf.Layer.CreateAnonymous("compose.usda")
        anon.TransferContent(root)
        layers = [self._layer(e) for e in reversed(list(epochs))]  # verified, and held open while composing
        anon.subLayerPaths.clear()
        for layer in ([extra] if extra is not None else []) + layers:
            anon.subLayerPaths.append(layer.identifier)
        try:
            return Usd.Stage.Open(anon)
        except Tf.ErrorException as exc:
            raise TwinStoreError(f"cannot compose twin {self._path}: {usd_message(exc)}") from None

    # ----------------------------------------------------------------------------------------------------------------
    # Writing an epoch

    def write_epoch(self, epoch_id: str, elements: Sequence[SetLike], provenance: dict,
                    region_of_view: tuple[np.ndarray, np.ndarray] | None = None,
                    segments: Sequence[Segment] = ()) -> Path:
        """Write one epoch layer holding the composite after this epoch (and the region of view its sensors
        measured, as a guide mesh under /RegionsOfView) ; return the layer path."""
        with self.writing():
            return self._write_epoch(epoch_id, elements, provenance, region_of_view, segments)

    def _write_epoch(self, epoch_id: str, elements: Sequence[SetLike], provenance: dict,
                     region_of_view: tuple[np.ndarray, np.ndarray] | None = None,
                     segments: Sequence[Segment] = ()) -> Path:
        existing = self._check_new_epoch(epoch_id, elements)
        layer = Sdf.Layer.CreateAnonymous(f"{epoch_id}.usdc")
        stage = self._stage_upto(existing, extra=layer)
        stage.SetEditTarget(Usd.EditTarget(layer))
        payloads = self._author_elements(stage, epoch_id, elements)
        if region_of_view is not None:
            guides.define_region_of_view(stage, epoch_id, *region_of_view)
        for seg in segments:
            guides.define_segment(stage, epoch_id, seg)
        layer.customLayerData = {"gdt": {"epoch": epoch_id, "state_names": Vt.StringArray(list(STATE_NAMES)),
                                         "reason_names": Vt.StringArray(list(REASON_NAMES)),
                                         "provenance_json": json.dumps(provenance, sort_keys=True, default=str)}}
        del stage  # a live stage would recompose, and warn, once the payload paths below are made relative
        relative_payloads(layer, self._path / EPOCH_DIR)
        target = self._epoch_file(epoch_id)
        digest = export_atomic(layer, target, ("layer-exported", "layer-renamed"))
        self._digests.remember(target, digest)
        rel = f"{EPOCH_DIR}/{epoch_id}.usdc"
        new_root = Sdf.Layer.CreateAnonymous("root.usda")
        new_root.TransferContent(self._root())
        new_root.subLayerPaths.insert(0, rel)
        # the layer's sha256, so readers can prove it is the file that was written (see integrity)
        data = dict(new_root.customLayerData)
        gdt = dict(data.get("gdt", {}))
        gdt["layer_sha256"] = {**dict(gdt.get("layer_sha256", {})), rel: digest,
                               **{f"{EPOCH_DIR}/{name}": d for name, d in payloads}}
        for name, d in payloads:
            self._digests.remember(self._path / EPOCH_DIR / name, d)
        new_root.customLayerData = {**data, "gdt": gdt}
        export_atomic(new_root, self.root_path, ("root-exported", "root-written"))
        return target

    def _check_new_epoch(self, epoch_id: str, elements: Sequence[SetLike]) -> list[str]:
        """The twin's epochs so far, after checking ``epoch_id`` and the set keys can be written."""
        if not Tf.IsValidIdentifier(epoch_id):
            raise TwinStoreError(f"epoch id {epoch_id!r} is not a valid identifier")
        existing = self.epochs()
        if epoch_id in existing:
            raise TwinStoreError(f"{self._path}: epoch {epoch_id!r} is already in the twin")
        keys = set_keys(elements)
        if len(set(keys)) != len(keys):
            raise TwinStoreError(f"epoch {epoch_id}: duplicate element set keys")
        return existing

    def _author_elements(self, stage: Usd.Stage, epoch_id: str, elements: Sequence[SetLike]
                         ) -> list[tuple[str, str]]:
        """Define the new sets and override the known ones; every known set must be restated. Large point sets go
        into payload layers of their own (``payloads``): their file names and sha256s are returned."""
        twin = stage.GetPrimAtPath(TWIN_PRIM)
        known = {c.GetName(): c for c in twin.GetChildren()} if twin else {}
        if not twin:
            UsdGeom.Xform.Define(stage, TWIN_PRIM)
        missing = sorted(k for k in set(known) - set(set_keys(elements)) if not _retired(known[k]))
        if missing:
            raise TwinStoreError(f"epoch {epoch_id}: element sets {missing} of earlier epochs are missing; removal is "
                                 f"expressed by state and visibility, never by dropping a set (only a set with no "
                                 f"visible element may be left out: it stays as it was)")
        written = []
        for es in elements:
            if es.key in known:
                if is_parted(known[es.key]):
                    override_parted_set(known[es.key], es, epoch_id)
                else:
                    override_element_set(known[es.key], whole(es), epoch_id)
                restate_preview(stage, es)
            elif wants_payload(es):
                written += define_payload_set(stage, es, self._path / EPOCH_DIR, epoch_id)
            else:
                define_element_set(stage, whole(es))
        return written

    # ----------------------------------------------------------------------------------------------------------------
    # Reading an epoch

    def read_segments(self, epoch_id: str, *, members: bool = True) -> list[Segment]:
        """The segments (connected changed elements) an epoch recorded, in id order; ``members=False``
        leaves out the member indices (a removed segment of a large scan has millions)."""
        return guides.read_segments(self._stage_upto(self._epochs_upto(epoch_id)), epoch_id, members=members)

    def read_region_of_view(self, epoch_id: str) -> tuple[np.ndarray, np.ndarray] | None:
        """The region of view stored with ``epoch_id`` (points, faces), or None when the epoch has none."""
        return guides.read_region_of_view(self._stage_upto(self._epochs_upto(epoch_id)), epoch_id)

    def read_epoch(self, epoch_id: str, keys: Iterable[str] | None = None) -> list[ElementSet]:
        """The composite as it was at ``epoch_id`` (only the layers up to it are composed); only the sets named in
        ``keys`` when given."""
        return list(self.iter_epoch(epoch_id, keys))

    def iter_epoch(self, epoch_id: str, keys: Iterable[str] | None = None, *, retired: bool = True
                   ) -> Iterator[ElementSet]:
        """The sets of the composite at ``epoch_id`` one at a time (payload sets too), so that a reader holds one
        set's arrays beside what it made of the others; only the sets named in ``keys`` when given; without the
        retired sets (no element visible, see ``retired_removed``) when ``retired`` is False."""
        stage = self._stage_upto(self._epochs_upto(epoch_id))
        twin = stage.GetPrimAtPath(TWIN_PRIM)
        wanted = None if keys is None else set(keys)
        for child in twin.GetChildren() if twin else []:
            if (wanted is None or child.GetName() in wanted) and (retired or not _retired(child)):
                yield read_set(child)

    def retired_removed(self, epoch_id: str) -> dict[str, int]:
        """Per retired set at ``epoch_id`` (one whose elements are all hidden: it never changes again, and later
        epochs are not handed it) how many of its elements left as removed; only their states are read."""
        stage = self._stage_upto(self._epochs_upto(epoch_id))
        twin = stage.GetPrimAtPath(TWIN_PRIM)
        removed = STATE_NAMES.index("removed")
        out = {}
        for child in twin.GetChildren() if twin else []:
            if _retired(child):
                states = set_values(child, "state")
                out[child.GetName()] = int(np.count_nonzero(states == removed))
        return out

    def branch(self, target: str | Path, epochs: Sequence[str]) -> tuple[TwinStore, int]:
        """A new twin folder at ``target`` holding this twin's oldest ``epochs``, each layer verified and then hard
        linked (copied where the filesystem cannot link); the new store and how many files were copied. The caller
        holds the lock of the twin the folder will become."""
        held = self.epochs()
        if list(epochs) != held[: len(epochs)]:
            raise TwinStoreError(f"{self._path}: {list(epochs)} are not its oldest epochs ({', '.join(held)})")
        for eid in epochs:
            self._layer(eid)
        copied = branch(self._path, Path(target), epochs, self.layer_digests())
        return TwinStore(Path(target), lock=False), copied

    def iter_sets(self, epoch_id: str) -> Iterator[LeanSet]:
        """The sets of the twin at ``epoch_id`` one at a time, each array read only when asked for (``lean``), with
        the same set as it was at the previous epoch; for summaries of twins too large to read whole."""
        upto = self._epochs_upto(epoch_id)
        stage = self._stage_upto(upto)
        before = self._stage_upto(upto[:-1]) if len(upto) > 1 else None
        yield from iter_lean_sets(stage, before)

    def identities(self, epoch_id: str) -> dict[str, dict[str, str]]:
        """Per set that has one, its identity outside the twin (IFC GlobalId and class, part name) at ``epoch_id``,
        read without the sets' arrays."""
        stage = self._stage_upto(self._epochs_upto(epoch_id))
        twin = stage.GetPrimAtPath(TWIN_PRIM)
        found = {child.GetName(): identity_of(child) for child in (twin.GetChildren() if twin else [])}
        return {key: ident for key, ident in found.items() if ident}

    def provenance(self, epoch_id: str) -> dict:
        """The provenance recorded with an epoch."""
        if epoch_id not in self.epochs():
            raise TwinStoreError(f"{self._path}: no epoch {epoch_id!r}")
        data = self._layer(epoch_id).customLayerData.get("gdt", {})
        try:
            return json.loads(data.get("provenance_json", "{}"))
        except json.JSONDecodeError as exc:
            raise TwinStoreError(f"{self._epoch_file(epoch_id)}: its provenance is not valid JSON ({exc.msg} at "
                                 f"line {exc.lineno}:{exc.colno})") from None

    # ----------------------------------------------------------------------------------------------------------------
    # History queries

    def history(self) -> list[EpochEntry]:
        """One entry per epoch, oldest first: its state counts and the provenance its layer records."""
        out = []
        for index, eid in enumerate(self.epochs()):
            prov = self.provenance(eid)
            counts = prov.get("counts") or count_states(self.read_epoch(eid))
            out.append(EpochEntry(eid, index, counts, prov))
        return out

    def diff(self, epoch_a: str, epoch_b: str) -> list[SetDiff]:
        """What changed from the twin at ``epoch_a`` to the twin at ``epoch_b``, per element set."""
        epochs = self.epochs()
        for e in (epoch_a, epoch_b):
            if e not in epochs:
                raise TwinStoreError(f"{self._path}: no epoch {e!r} (epochs: {', '.join(epochs) or 'none'})")
        before = {e.key: e for e in self.read_epoch(epoch_a)}
        return [set_diff(before.get(es.key), es) for es in self.read_epoch(epoch_b)]

    # ----------------------------------------------------------------------------------------------------------------
    # Export

    def flatten(self, epoch_id: str, out: str | Path) -> Path:
        """Write the twin as it was at ``epoch_id`` as one flat USD file, with every epoch's provenance copied in."""
        out = Path(out)
        upto = self._epochs_upto(epoch_id)
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
        export_atomic(flat, out)
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


def _retired(prim: Usd.Prim) -> bool:
    """Whether a set has no visible element (the whole prim is invisible): a hidden element never comes back, so
    such a set keeps its values for good and a later epoch need not restate it."""
    return UsdGeom.Imageable(prim).GetVisibilityAttr().Get() == UsdGeom.Tokens.invisible
