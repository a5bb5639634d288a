"""Correspondences between recent elements and the twin (paper Sec. 4.2.2):

- ``point_to_point``, ``point_to_mesh``, ``mesh_to_point``, ``mesh_to_mesh``: the paper's four uncertainty-directed
  cases (see ``directed``), each for its kinds of data;
- ``auto``: picks the case per recent dataset and per reference item from their kinds, so a workflow need not say;
- ``nearest``: the plain baseline, each element (a point, or a facet's centroid) matched to the closest visible
  reference element.

Elements with no correspondence inside the search space are kept and marked (no candidate): the threshold then
makes them new, never drops them.
"""

from __future__ import annotations

from gdt_pipeline import StageSpec, hookimpl

from . import directed_search, nearest
from .directed_search import DirectedParams
from .nearest import NearestParams

__all__ = ["DirectedParams", "NearestParams", "gdt_stages"]


@hookimpl
def gdt_stages() -> list[StageSpec]:
    """The built-in correspondence estimators."""
    return [nearest.SPEC, directed_search.POINT_TO_POINT, directed_search.POINT_TO_MESH, directed_search.MESH_TO_POINT,
            directed_search.MESH_TO_MESH, directed_search.AUTO]
