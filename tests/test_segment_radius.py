"""The fusion's default segment radius stays at a scale the radius guard accepts, however noisy the scan: a ToF at
4.5 m (σ 30 cm along the beam) once made the default radius refuse itself."""

from __future__ import annotations

import numpy as np

from stages.fusion._segments import SegmentParams, segment_labels


def test_a_noisy_scans_default_radius_groups_objects_instead_of_refusing() -> None:
    rng = np.random.default_rng(0)
    # two objects 2.8 m apart in a 4 m scene, 1500 changed points each, σ 0.5 m (1.5σ is over a tenth of the extent)
    a = rng.normal([0.0, 0.0, 0.0], 0.05, (1500, 3))
    b = rng.normal([2.0, 2.0, 0.0], 0.05, (1500, 3))
    corner = np.array([[-1.0, -1.0, -0.5], [3.0, 3.0, 0.5]])
    pos = np.vstack([a, b, corner])
    label = segment_labels(pos, np.full(len(pos), 0.5), SegmentParams())
    assert len(set(label[:1500])) == 1 and len(set(label[1500:3000])) == 1 and label[0] != label[1500]
