"""3-D tiles with halos: the grid, box queries, cutting an epoch's slots to a tile and merging tiles' core results
(``docs/scale.md``). The runner (``runner.tiled``) drives them; executors (``gdt_executors`` plugins) run the tiles."""

from .candidate_sink import CandidateSink, candidate_places
from .crop import crop_composite, crop_rov, in_box, lookup, take_candidates, take_dataset
from .grid import TileGrid, grid_for, size_for_budget
from .index import CellIndex, members_of
from .merge import ElementOrder, merge_change, merge_correspondences, merge_recent

__all__ = ["CandidateSink", "CellIndex", "ElementOrder", "TileGrid", "candidate_places", "crop_composite", "crop_rov",
           "grid_for", "in_box", "lookup", "members_of", "merge_change", "merge_correspondences", "merge_recent",
           "size_for_budget", "take_candidates", "take_dataset"]
