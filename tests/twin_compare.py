"""Two twins compared element set by element set, and the sha256 of a twin's layer files (the append tests)."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np

from twin_store import TwinStore


def layer_digests(twin: Path) -> dict[str, str]:
    """sha256 of every layer file of a twin (epoch layers and payloads), by path relative to it."""
    return {p.relative_to(twin).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(twin.rglob("*.usdc"))}


def assert_same_twins(a: Path, b: Path) -> None:
    """Every element set of every epoch equal bitwise: geometry, covariances, scores, states, visibility, source
    epochs, reasons (NaN equal to NaN)."""
    sa, sb = TwinStore.open(a), TwinStore.open(b)
    assert sa.epochs() == sb.epochs()
    for eid in sa.epochs():
        x, y = {s.key: s for s in sa.read_epoch(eid)}, {s.key: s for s in sb.read_epoch(eid)}
        assert x.keys() == y.keys(), eid
        for key in x:
            for f in dataclasses.fields(x[key]):
                va, vb = getattr(x[key], f.name), getattr(y[key], f.name)
                if isinstance(va, np.ndarray) or isinstance(vb, np.ndarray):
                    assert va is not None and vb is not None and va.shape == vb.shape, (eid, key, f.name)
                    assert np.array_equal(va, vb, equal_nan=va.dtype.kind == "f"), (eid, key, f.name)
                else:
                    assert va == vb, (eid, key, f.name)
