"""The names and codes a twin store writes: change-state and fusion-reason codes, display colours, file and prim
paths, and the documentation attached to the per-element primvars."""

from __future__ import annotations

import numpy as np

# not_comparable: a recent element where the reference has no data (nothing to compare it with), or a known element
# that nothing recent tested (no region of view, no confirming match): neither unchanged nor changed
STATE_NAMES: tuple[str, ...] = ("unchanged", "new", "removed", "outside_rov", "not_comparable")
STATE_COLORS = np.array([[0.7, 0.7, 0.7], [0.1, 0.75, 0.2], [0.85, 0.1, 0.1], [0.3, 0.45, 0.9], [0.95, 0.65, 0.1]],
                        dtype=np.float32)
ROOT_NAME = "twin.usda"
EPOCH_DIR = "epochs"
ROV_PRIM = "/RegionsOfView"
SEGMENTS_PRIM = "/Segments"
TWIN_PRIM = "/Twin"

# why an element is (or is not) in the composite after an epoch's fusion; the codes are gdt:fusionReason
REASON_NAMES: tuple[str, ...] = (
    "baseline",            # 0: the element came with the first epoch (or no fusion decided about it)
    "kept",                # 1: known element, still in the composite
    "new",                 # 2: changed element of the epoch's data, came in
    "removed",             # 3: known element in the region of view that no recent data matches: hidden
    "outside_rov",         # 4: known element outside the region of view: kept as it was
    "replaced",            # 5: known element imaged by more precise (or, by policy, newer) data: hidden
    "replaces",            # 6: unchanged recent element that took the place of known data
    "known_more_precise",  # 7: unchanged recent element hidden: the known data it images is as precise or better
    "design_stays",        # 8: unchanged recent element hidden: it images design (CAD) geometry, which stays
    "known_stays",         # 9: unchanged recent element hidden: the policy keeps known data (or it images none)
    "extends",             # 10: recent element where the twin had no data (not comparable): came in
)

DOC_UNCERTAINTY = "Scalar uncertainty per element for display: RMS standard deviation (twin units)."
DOC_SCORE = "Change score per element (dissimilarity); NaN where not scored."
DOC_STATE = "Per-element change state code: " + ", ".join(f"{i}={n}" for i, n in enumerate(STATE_NAMES)) + "."
DOC_SOURCE_EPOCH = "Index of the epoch that supplied the element."
DOC_VISIBLE = "Element is part of the composite at this epoch; hidden elements stay in the history."
DOC_COVARIANCE = ("Per-element positional covariance, 6 floats per element in the order xx xy xz yy yz zz "
                  "(twin units²).")
DOC_HALF_WIDTHS = "GUM rectangular error limits: box half-widths per element (twin units)."
DOC_P_VALUE = "p-value of the change test per element (NaN where not tested)."
DOC_REASON = ("Per-element fusion reason code: " + ", ".join(f"{i}={n}" for i, n in enumerate(REASON_NAMES))
              + ". Hidden elements keep the reason they left with.")
DOC_RATIO = ("The fusion rule's number per element: √det Σ of the new data over that of the known data it was "
             "compared with (replaced, replaces, known_more_precise); NaN where no comparison was made.")
DOC_AREA_SEEN = ("Share of each element's area a station of the epoch saw (measured surface at it, or seen through "
                 "it), from samples spread over the facet; NaN where the region of view judged elements whole.")
DOC_AREA_REMOVED = ("Share of each element's area a station saw through (measured surface clearly behind it): the "
                    "removed part; the element is removed when more of it was seen through than found present.")
DOC_ROTATION = "Box axes per element: a row-major 3x3 rotation whose columns are the axes."

# The run record a `gdt run` writes into the twin folder (seed, packages, cache keys, layer sha256s); the twin owns it.
RUN_LOCK_NAME = "gdt.lock"
DOC_INTENSITY = "Return intensity per element as the scan file gave it (E57, LAS), in the file's own scale."
DOC_SCAN_COLOR = "Colour per element as the scan file gave it (E57, LAS RGB), 0..1 (displayColor shows the change)."
# customData key of a set's identity outside the twin: part name, IFC GlobalId and class, E57 scan guid
IDENTITY_KEY = "gdt:identity"
DOC_CLASSIFICATION = "ASPRS class per point as the LAS/LAZ file gave it (2 ground, 6 building, ...)."
# customData key of what brought a set in: the epoch, its role (as-designed, as-is) and the dataset's name, so that a
# later epoch reads back the composite item a run handed on
ITEM_KEY = "gdt:item"


def state_colours(state: np.ndarray) -> np.ndarray:
    """The colour (0..1) of each change state code; codes past the table take its last colour."""
    return STATE_COLORS[np.minimum(np.asarray(state, dtype=np.uint8), len(STATE_COLORS) - 1)]
