"""``gdt eval``: run a workflow on a simulated scene and score each epoch against the scene's ground truth, side by
side with the peers on the same data.

Truth lives beside each simulated scan (``<scan>_truth.npz``: per point whether it lies on changed geometry, the
object hit, the noise-free position) and per epoch in the scene directory (``truth_<epoch>.npz``: per facet of the
previous epoch's objects whether it was removed and whether a station could see it, per object its state).

Per as-is epoch this reports, for this workflow and for each peer:

- precision, recall and F1 of the points marked changed, and the false-alarm rate (the only meaningful figure of an
  epoch without true change);
- recall of removed geometry and the false-removal rate on geometry no station could see;
- per new or removed object whether it was found, and for new ones the centre error of the found cluster;
- the composite's distance to the true as-is geometry (mean and 95th percentile).

Peers: cloud-to-cloud / cloud-to-mesh distance to the previous epoch's twin with a fixed threshold, py4dgeo's M3C2
(radius from Lague et al.'s rule of at least 30 points per cylinder, no registration error: the documented defaults)
and M3C2-EP (on a subsample: it runs at a few hundred core points per second). For C2C and M3C2 the best threshold of
a sweep on the truth is also reported: an upper bound no user has.

Modules: ``driver`` (the run), ``epoch`` (one epoch's scoring), ``truth`` (the scene's truth files), ``metrics``
(precision/recall and threshold sweeps), ``peer_runs`` and ``peers`` (the peers), ``scoring`` (removal, objects,
segments, composite), ``tables`` and ``report`` (the output), ``workflows`` (fusion variants, missing scenes).
The engine and the stages never import this package.
"""

from .driver import evaluate
from .metrics import prf, sweep, threshold_candidates
from .peer_runs import C2C_TAU, PEERS
from .report import write_report
from .tables import format_table
from .workflows import FUSIONS, missing_scene, with_fusion

__all__ = ["C2C_TAU", "FUSIONS", "PEERS", "evaluate", "format_table", "missing_scene", "prf", "sweep",
           "threshold_candidates", "with_fusion", "write_report"]
