"""Candidate matches of a recent dataset's elements in the reference, and the operations on them: a subset of the
candidates and the concatenation of several sets (tiles).

Which fields hold one row per candidate is said once, in each field's metadata (``PER_CANDIDATE``), and ``take``
and ``concat`` carry every such field: a field added later (here or in a subclass) is carried by sorting, cropping
and merging without touching them.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import GdtError
from ..memory import return_freed_memory
from .arrays import frozen_array, index_column, index_dtype
from .uncertainty import GaussianUncertainty, Uncertainty, concat_uncertainty

# a field with one row per candidate; ``rows_of`` names the field whose rows its values index (−1: none)
PER_CANDIDATE: dict[str, Any] = {"per": "candidate"}
REF_ROWS: dict[str, Any] = {"per": "candidate", "rows_of": "ref_uncertainty"}
# ``element``'s default until ``__post_init__`` makes it "candidate m is element m" (a field is never None)
_EACH_ITS_OWN = np.zeros(0, dtype=np.int64)


def _per_candidate(f: dataclasses.Field[Any]) -> bool:
    return bool(f.metadata.get("per") == "candidate")


@dataclass(frozen=True)
class Correspondences:
    """Candidate matches of the elements of one recent dataset in the reference.

    Each of the M candidates belongs to query element ``element[m]`` (default: candidate m is element m), compares
    the query at ``query_position[m]`` (default: the element's position; facet samples use their own) with the
    reference at ``position[m]`` whose uncertainty is that of reference element ``ref_element[m]`` of item
    ``ref_item[m]``, or row ``ref_row[m]`` of ``ref_uncertainty`` where that is ≥ 0 (a mixture of neighbours;
    default: row m for every candidate when ``ref_uncertainty`` is given). ``query_uncertainty``, when given, holds
    the query's uncertainty per candidate (a neighbourhood expectation's, which differs from the element's own);
    it comes with ``query_position``. ``ref_item`` −1: no
    correspondence inside the search space. Distance stages score every candidate and keep, per element, the
    lowest score (the paper: "the candidate with the lower change score wins").
    """

    query: int
    ref_item: np.ndarray = field(metadata=PER_CANDIDATE)
    ref_element: np.ndarray = field(metadata=PER_CANDIDATE)
    position: np.ndarray = field(metadata=PER_CANDIDATE)
    distance: np.ndarray = field(metadata=PER_CANDIDATE)
    method: str = ""
    element: np.ndarray = field(default_factory=lambda: _EACH_ITS_OWN, metadata=PER_CANDIDATE)
    query_position: np.ndarray | None = field(default=None, metadata=PER_CANDIDATE)
    ref_uncertainty: Uncertainty | None = None
    n_elements: int | None = None
    ref_row: np.ndarray | None = field(default=None, metadata=REF_ROWS)
    query_uncertainty: Uncertainty | None = field(default=None, metadata=PER_CANDIDATE)

    def __post_init__(self) -> None:
        object.__setattr__(self, "ref_item", frozen_array(self.ref_item, index_column(self.ref_item), (None,),
                                                          "ref_item"))
        m = len(self.ref_item)
        if self.ref_uncertainty is not None:
            rows = np.arange(m) if self.ref_row is None else self.ref_row
            object.__setattr__(self, "ref_row", frozen_array(rows, index_column(rows), (m,), "ref_row"))
        object.__setattr__(self, "ref_element", frozen_array(self.ref_element, index_column(self.ref_element), (m,),
                                                             "ref_element"))
        object.__setattr__(self, "position", frozen_array(self.position, np.float64, (m, 3), "matched position"))
        object.__setattr__(self, "distance", frozen_array(self.distance, np.float64, (m,), "distance"))
        if self.element is _EACH_ITS_OWN:
            object.__setattr__(self, "element", frozen_array(np.arange(m, dtype=index_dtype(m)), index_dtype(m), (m,),
                                                             "candidate element"))
            object.__setattr__(self, "n_elements", m if self.n_elements is None else self.n_elements)
        else:
            object.__setattr__(self, "element", frozen_array(self.element, index_column(self.element), (m,),
                                                             "candidate element"))
            if self.n_elements is None:
                raise ValueError("correspondences with an element map need n_elements")
        if self.query_position is not None:
            object.__setattr__(self, "query_position",
                               frozen_array(self.query_position, np.float64, (m, 3), "query position"))
        if self.query_uncertainty is not None:
            if self.query_position is None:
                raise ValueError("correspondences with a query uncertainty per candidate need query positions")
            q_rows = self.query_uncertainty.rows
            if q_rows not in (1, m):
                raise ValueError(f"query uncertainty: {q_rows} rows for {m} candidates (give 1, or one per candidate)")

    @property
    def found(self) -> np.ndarray:
        """Mask of the candidates that are a correspondence."""
        return self.ref_item >= 0

    def element_found(self) -> np.ndarray:
        """Mask of the query elements with at least one correspondence."""
        out = np.zeros(self.n_elements or 0, dtype=bool)
        out[self.element[self.found]] = True
        return out

    def take(self, sel: np.ndarray) -> Correspondences:
        """The candidates ``sel`` (indices, in the order given), with every per-candidate field; the rows of
        ``ref_uncertainty`` stay as they are (``ref_row`` still indexes them)."""
        values = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if _per_candidate(f) and value is not None:
                value = value[sel] if isinstance(value, np.ndarray) else value.take(sel)
            values[f.name] = value
        return type(self)(**values)

    @classmethod
    def concat(cls, pieces: Sequence[Correspondences], query: int, n_elements: int) -> Correspondences:
        """The candidates of ``pieces`` one after the other (tiles' results in global numbering): every
        per-candidate field joined, the reference rows of each piece offset past the earlier pieces' rows."""
        sizes = [len(p.ref_item) for p in pieces]
        kind = type(pieces[0]) if pieces else cls
        values: dict[str, Any] = {"query": query, "n_elements": n_elements,
                                  "method": pieces[0].method if pieces else ""}
        for name, parts in field_parts(pieces, kind, values).items():
            values[name] = np.concatenate(parts) if isinstance(parts[0], np.ndarray) else \
                concat_uncertainty(parts, sizes)
        if not pieces:
            values.update(ref_item=np.zeros(0), ref_element=np.zeros(0), position=np.zeros((0, 3)),
                          distance=np.zeros(0), element=np.zeros(0, np.int64))
        return kind(**values)

    @classmethod
    def scattered(cls, pieces: list[Correspondences], where: Sequence[np.ndarray], query: int, n_elements: int,
                  release: bool = False) -> Correspondences:
        """The candidates of ``pieces``, candidate j of piece i at ``where[i][j]`` (a permutation of all of them):
        ``concat`` then ``take`` without the joined copy. ``release`` empties ``pieces`` and lets go of each piece's
        field once it is in place, so that a run merging tiles holds the merged candidates and the rest of the
        tiles', not both in full (three copies with ``concat`` and ``take``)."""
        if not pieces:
            return cls.concat(pieces, query, n_elements)
        total = sum(len(p.ref_item) for p in pieces)
        kind = type(pieces[0])
        values: dict[str, Any] = {"query": query, "n_elements": n_elements, "method": pieces[0].method}
        columns = field_parts(pieces, kind, values)
        if release:
            pieces.clear()
        for name, parts in columns.items():
            values[name] = scatter_rows(parts, where, total)
            if release:
                return_freed_memory()  # the pieces' pages of this field, before the next field's are taken
        return kind(**values)


def field_parts(pieces: Sequence[Any], kind: type, values: dict[str, Any], sizes: Sequence[int] | None = None
                ) -> dict[str, list[Any]]:
    """Per per-candidate field that some piece carries (and ``values`` does not hold yet), each piece's part; row
    indices offset into the pieces' joined row model, which goes into ``values``. An error when pieces disagree on
    whether they carry a field. ``sizes``: the pieces' candidates, where their ``ref_item`` is not at hand."""
    sizes = [len(p.ref_item) for p in pieces] if sizes is None else list(sizes)
    out: dict[str, list[Any]] = {}
    for f in dataclasses.fields(kind):
        if f.name in values or not _per_candidate(f):
            continue
        parts = [getattr(p, f.name) for p in pieces]
        if all(v is None for v in parts):
            continue
        if "rows_of" in f.metadata:  # pieces without the row model have no rows to index: −1
            values[f.metadata["rows_of"]], rows = _joined_rows(pieces, f.metadata["rows_of"], f.name)
            parts = np.split(rows, np.cumsum(sizes)[:-1])
        elif any(v is None for v in parts):
            raise GdtError(f"tiles disagree on whether candidates carry {f.name!r}")
        out[f.name] = parts
    return out


def _joined_rows(pieces: Sequence[Correspondences], rows_of: str, name: str) -> tuple[Any, np.ndarray]:
    """The row models of the pieces that have them, joined, and every piece's row indices offset into the join."""
    models = [getattr(p, rows_of) for p in pieces if getattr(p, rows_of) is not None]
    rows, offset = [], 0
    for p in pieces:
        model = getattr(p, rows_of)
        if model is None:
            rows.append(np.full(len(p.ref_item), -1, dtype=np.int64))
            continue
        index = getattr(p, name)
        rows.append(np.where(index >= 0, index + np.int64(offset), -1))  # an int32 index plus an offset could wrap
        offset += model.rows
    return concat_uncertainty(models, [m.rows for m in models]), np.concatenate(rows)


def scatter_rows(parts: list[Any], where: Sequence[np.ndarray], total: int) -> Any:
    """One per-candidate field of the pieces put in place, row j of piece i at ``where[i][j]`` (each piece's part let
    go once written)."""
    first = parts[0]
    if isinstance(first, np.ndarray):
        out = np.empty((total, *first.shape[1:]), dtype=np.result_type(*parts))
        for i, rows in enumerate(where):
            out[rows] = parts[i]
            parts[i] = None
        out.setflags(write=False)  # frozen as it is, the merged candidates take it without a copy (8 B a candidate)
        return out
    if isinstance(first, GaussianUncertainty) and all(
            isinstance(u, GaussianUncertainty) and u.rows == len(rows) and u.dof == first.dof
            for u, rows in zip(parts, where, strict=True)):
        cov = np.empty((total, 3, 3))
        for i, rows in enumerate(where):
            cov[rows] = parts[i].cov
            parts[i] = None
        cov.setflags(write=False)
        return GaussianUncertainty.trusted(cov, first.dof)
    joined = concat_uncertainty(parts, [len(rows) for rows in where])  # other models: joined, then ordered
    order = np.empty(total, dtype=np.int64)
    order[np.concatenate(where)] = np.arange(total)
    return joined.take(order)
