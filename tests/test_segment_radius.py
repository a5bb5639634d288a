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


def test_a_dense_noisy_scans_default_radius_is_narrowed_within_the_pair_limit() -> None:
    from scipy.spatial import cKDTree

    from gdt_pipeline.geometry.extent import MAX_PAIRS

    rng = np.random.default_rng(1)
    # two dense patches of 15 000 changed points 2 m apart in a 5.7 m scene: 5 % of the extent (29 cm) spans each
    # patch whole, 2.2e8 pairs, which the guard refused
    a = np.column_stack([rng.uniform(0, 0.3, (15_000, 2)), rng.normal(0, 0.01, 15_000)])
    b = a + np.array([2.0, 2.0, 0.0])
    corner = np.array([[-1.0, -1.0, -0.5], [3.0, 3.0, 0.5]])
    pos = np.vstack([a, b, corner])
    label = segment_labels(pos, np.full(len(pos), 0.5), SegmentParams())
    assert len(set(label[:15_000])) == 1 and len(set(label[15_000:30_000])) == 1 and label[0] != label[15_000]
    tree = cKDTree(pos)
    old_default = 0.05 * np.linalg.norm(np.ptp(pos, axis=0))
    assert (tree.count_neighbors(tree, old_default) - len(pos)) / 2 > MAX_PAIRS  # refused by the guard
