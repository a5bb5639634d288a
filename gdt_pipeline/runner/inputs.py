"""Reading an epoch's inputs: the reader each file selects, checks that the geometry is usable, the unit scale."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from ..errors import GdtError, InputError, StageError
from ..names import UNITS, identifier
from ..plugins import ReaderSpec, ReadRequest, Registry
from ..types import Dataset, SourceInfo
from .plan import EpochPlan, InputPlan, RunPlan
from .poses import resolve_poses


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    """sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def relative_to_workflow(path: Path, base: Path) -> str:
    """A path relative to the workflow folder when below it (host-independent provenance), else absolute."""
    try:
        return path.resolve().relative_to(base.resolve()).as_posix()
    except ValueError:
        return str(path.resolve())


def check_dataset(ds: Dataset, where: str) -> None:
    """Refuse an empty dataset or one with non-finite coordinates, naming the rows."""
    if ds.n_elements == 0 or len(ds.points) == 0:
        raise InputError(f"{where}: the {'mesh has no faces' if ds.faces is not None else 'point cloud is empty'}")
    bad = ~np.isfinite(ds.points).all(axis=1)
    if bad.any():
        first = np.flatnonzero(bad)[:5].tolist()
        raise InputError(f"{where}: {int(bad.sum())} of {len(ds.points)} coordinates are NaN or infinite "
                         f"(first rows {first}); clean the file or remove those points")


def _without_path(message: str, path: Path) -> str:
    """A reader's message without its leading file path, which ``where`` already names."""
    for prefix in (f"{path}: ", f"{path.resolve()}: "):
        if message.startswith(prefix):
            return message[len(prefix):]
    return message


def _check_file(path: Path, where: str) -> None:
    """Name what is wrong with the path itself before any reader is asked."""
    if path.is_dir():
        raise InputError(f"{where}: is a directory, not a file")
    if not path.exists():
        raise InputError(f"{where}: file not found")
    if path.stat().st_size == 0:
        raise InputError(f"{where}: the file is empty (0 bytes)")


def _select_reader(path: Path, registry: Registry, kind: str | None, reader: str | None, where: str) -> ReaderSpec:
    if reader:
        return registry.reader(reader)
    cands = registry.readers_for(path, kind)
    if not cands:
        raise InputError(f"{where}: no installed reader accepts this file")
    return cands[0]


def _named_parts(parts: list[Dataset], name: str, where: str) -> list[Dataset]:
    """The datasets of a multi-part file named ``<input name>_<part>`` (unique, USD-safe); the part's own name is
    kept in ``meta["name"]``."""
    out, seen = [], set()
    for k, ds in enumerate(parts):
        if not isinstance(ds, Dataset):
            raise StageError(f"{where}: part {k} read as {type(ds).__name__}, not a Dataset")
        base = identifier(f"{name}_{ds.name}") if ds.name else f"{name}_{k}"
        unique, n = base, 2
        while unique in seen:
            unique, n = f"{base}_{n}", n + 1
        seen.add(unique)
        out.append(dataclasses.replace(ds, name=unique, meta={"name": ds.name, **ds.meta}))
    return out


def reader_params(spec: ReaderSpec, params: dict[str, Any] | None, where: str) -> Any:
    """A reader's validated parameters from an input's ``with:`` (its defaults when there is none)."""
    try:
        return spec.params.model_validate(params or {})
    except ValidationError as exc:
        what = "; ".join(f"with.{'.'.join(str(p) for p in e['loc'])}: {e['msg']}"
                         for e in exc.errors(include_url=False))
        raise InputError(f"{where}: reader {spec.name!r}: {what}") from None


def read_datasets(path: Path, registry: Registry, *, name: str, role: str = "as-is", kind: str | None = None,
                  reader: str | None = None, digest: str = "", where: str | None = None,
                  params: dict[str, Any] | None = None) -> list[Dataset]:
    """Read one file with the reader its extension (or ``reader``) selects and check the geometry is usable: one
    dataset, or one per part or scan of a file that holds several (named ``<name>_<part>``)."""
    where = where or str(path)
    _check_file(path, where)
    spec = _select_reader(path, registry, kind, reader, where)
    request = ReadRequest(path, name, role, kind, digest, params=reader_params(spec, params, where))
    try:
        read = spec.read(request)
    except GdtError as exc:
        raise InputError(f"{where}: {_without_path(str(exc), path)}") from exc
    except (KeyboardInterrupt, SystemExit, GeneratorExit, MemoryError):
        raise
    except BaseException as exc:
        # BaseException, not Exception: parsers written in Rust (lazrs through pyo3) raise a PanicException that
        # derives from BaseException, and a file that panics a parser is still bad input, not a bug of ours.
        raise InputError(f"{where}: reader {spec.name!r} failed: {type(exc).__name__}: {exc}") from exc
    if isinstance(read, list):
        if not read:
            raise InputError(f"{where}: reader {spec.name!r} found nothing to read in the file")
        parts = _named_parts(read, name, where)
    elif isinstance(read, Dataset):
        parts = [read]
    else:
        raise StageError(f"{where}: reader {spec.name!r} returned {type(read).__name__}, not a Dataset")
    for ds in parts:
        check_dataset(ds, where if len(parts) == 1 else f"{where}, part {ds.meta.get('name', ds.name)!r}")
    source = SourceInfo(path=str(path), sha256=digest, reader=spec.name, notes=dict(request.notes))
    return [dataclasses.replace(ds, source=source) for ds in parts]


def read_dataset(path: Path, registry: Registry, *, name: str, role: str = "as-is", kind: str | None = None,
                 reader: str | None = None, digest: str = "", where: str | None = None,
                 params: dict[str, Any] | None = None) -> Dataset:
    """Read a file that holds one dataset (:func:`read_datasets`); a file of several parts is an error."""
    parts = read_datasets(path, registry, name=name, role=role, kind=kind, reader=reader, digest=digest, where=where,
                          params=params)
    if len(parts) != 1:
        raise InputError(f"{where or path}: holds {len(parts)} datasets ({', '.join(d.name for d in parts[:5])}"
                         f"{', ...' if len(parts) > 5 else ''}); one is expected here")
    return parts[0]


def _data_units(parts: list[Dataset], inp: InputPlan, where: str) -> str:
    """The units an input's coordinates are in: those its reader states (``req.report(units=...)``: E57 is metres by
    the standard, a CAD reader converts the file's own length unit), else the input's ``units:``. A ``units:``
    written on the input that differs from the reader's contradicts the file: an error naming both."""
    stated = parts[0].source.notes.get("units") if parts[0].source else None
    if stated is None:
        return inp.units
    if stated not in UNITS:
        raise StageError(f"{where}: the reader states units {stated!r}, not one of {', '.join(UNITS)}")
    if inp.units_given and inp.units != stated:
        raise InputError(f"{where}: `units: {inp.units}` contradicts the reader, which returns the data in {stated!r} "
                         f"(the file's own length unit, converted): remove `units:` from this input")
    return stated


def read_input(plan: RunPlan, registry: Registry, epoch: EpochPlan, i_index: int, digest: str
               ) -> tuple[list[Dataset], list[dict[str, Any]]]:
    """Input ``i_index`` of an epoch, read, checked and scaled to the twin's units, each dataset with its station
    (:func:`resolve_poses`); and per dataset the record of where its pose came from."""
    inp = epoch.inputs[i_index]
    where = f"epoch {epoch.id}, input {i_index} ({inp.path})"
    parts = read_datasets(inp.path, registry, name=inp.name, role=epoch.role, kind=inp.kind, reader=inp.reader,
                          digest=digest, where=where, params=inp.params)
    units = _data_units(parts, inp, where)
    scale = UNITS[units] / UNITS[plan.units]
    source = SourceInfo(path=relative_to_workflow(inp.path, plan.base_dir), sha256=digest, units=units,
                        scale=scale, reader=parts[0].source.reader if parts[0].source else "",
                        notes=parts[0].source.notes if parts[0].source else {})
    scaled = [dataclasses.replace(ds, points=ds.points * scale if scale != 1.0 else ds.points, source=source)
              for ds in parts]
    return resolve_poses(scaled, inp.path, inp.viewpoints, scale, where)


def input_digests(plan: RunPlan, epochs: list[EpochPlan] | None = None) -> dict[tuple[int, int], str]:
    """sha256 of every input of ``epochs`` (default: all of the plan's), by (epoch index, input index), read before
    anything runs."""
    digests: dict[tuple[int, int], str] = {}
    for epoch in plan.epochs if epochs is None else epochs:
        for i_index, inp in enumerate(epoch.inputs):
            try:
                digests[(epoch.index, i_index)] = sha256_file(inp.path)
            except OSError as exc:
                raise InputError(f"epoch {epoch.id}, input {i_index} ({inp.path}): cannot read: "
                                 f"{exc.strerror}") from exc
    return digests
