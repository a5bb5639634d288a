"""The per-element values the LAS/LAZ and PLY exports carry as named scalar fields (CloudCompare shows them as scalar
fields): one table of names, types and descriptions for both formats, and the values of a set's elements."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from twin_store import REASON_NAMES, STATE_NAMES, ElementSet

from .errors import GdtError

# name, numpy type, description (LAS extra-bytes descriptions hold 32 characters, so both formats say this much)
VALUE_FIELDS: tuple[tuple[str, type[np.generic], str], ...] = (
    ("change_state", np.uint8, "gdt:changeState code (0 same)"),
    ("change_score", np.float32, "dissimilarity score (NaN: none)"),
    ("p_value", np.float32, "p-value of the test (NaN: none)"),
    ("uncertainty", np.float32, "RMS sigma of the position"),
    ("source_epoch", np.int32, "index of the epoch it came from"),
    ("fusion_reason", np.uint8, "fusion reason code"),
    ("fusion_ratio", np.float32, "sqrt det cov ratio new/known"),
)
# the names behind the codes, for formats with room to spell them out (PLY comments)
CODE_NAMES: dict[str, tuple[str, ...]] = {"change_state": STATE_NAMES, "fusion_reason": REASON_NAMES}


def element_values(es: ElementSet, selected: np.ndarray) -> dict[str, np.ndarray]:
    """Each field's values for the ``selected`` elements of ``es``, typed as in VALUE_FIELDS (NaN or 0 where unset)."""
    n = int(np.count_nonzero(selected))
    nan = np.full(n, np.nan, dtype=np.float32)
    values = {
        "change_state": np.asarray(es.state)[selected],
        "change_score": np.asarray(es.score)[selected],
        "p_value": nan if es.p_value is None else np.asarray(es.p_value)[selected],
        "uncertainty": np.asarray(es.uncertainty_summary)[selected],
        "source_epoch": np.asarray(es.source_epoch)[selected],
        "fusion_reason": np.zeros(n, np.uint8) if es.reason is None else np.asarray(es.reason)[selected],
        "fusion_ratio": nan if es.reason_ratio is None else np.asarray(es.reason_ratio)[selected],
    }
    return {name: values[name].astype(dtype, copy=False) for name, dtype, _ in VALUE_FIELDS}


@contextlib.contextmanager
def written_in_place(path: Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to, renamed onto ``path`` once the block succeeds: a reader never
    sees half a file, and a failed write leaves the old one (an error naming ``path``)."""
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
    except Exception as exc:
        tmp.unlink(missing_ok=True)
        raise GdtError(f"could not write {path}: {type(exc).__name__}: {exc}") from exc
    os.replace(tmp, path)
