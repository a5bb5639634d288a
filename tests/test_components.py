"""The radius graph's components found piece by piece: the same labels as scipy's, without holding the pairs."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from gdt_pipeline.geometry.components import radius_components


def _scipy_labels(points: np.ndarray, radius: float) -> tuple[np.ndarray, int]:
    tree = cKDTree(points)
    pairs = tree.query_pairs(radius, output_type="ndarray")
    n = len(points)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1], len(pairs)


@pytest.mark.parametrize(("n", "radius", "per_piece"), [(1, 0.1, 10), (5_000, 0.02, 500), (20_000, 0.015, 3_000),
                                                        (3_000, 0.05, 10**7)])
def test_labels_are_scipys_whatever_the_pieces(n: int, radius: float, per_piece: int) -> None:
    rng = np.random.default_rng(n)
    points = rng.random((n, 3))
    points[: n // 10] = np.round(points[: n // 10] * 50) / 50  # a 0.02 grid: pairs exactly r apart at r = 0.02
    want, pairs = _scipy_labels(points, radius)
    tree = cKDTree(points)
    got = radius_components(tree, radius, per_piece)
    assert np.array_equal(got, want)
    counted = radius_components(tree, radius, per_piece, listed=int(tree.count_neighbors(tree, radius)))
    assert np.array_equal(counted, want)  # with the caller's count, as the fusion passes check_radius's
    assert pairs > 0 or n == 1


def test_no_points_no_labels() -> None:
    assert radius_components(cKDTree(np.zeros((0, 3))), 1.0).shape == (0,)


def test_memory_is_a_piece_not_the_pairs() -> None:
    rng = np.random.default_rng(7)
    points = rng.random((60_000, 3)) * [1.0, 1.0, 0.01]  # a thin slab: about 40 pairs a point
    tree = cKDTree(points)
    radius = 0.016
    pairs = (int(tree.count_neighbors(tree, radius)) - len(points)) // 2
    tracemalloc.start()
    labels = radius_components(tree, radius, pairs_per_piece=100_000)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert pairs > 1_000_000
    assert peak < 16 * pairs / 2  # under half of what the pair list alone held (16 B a pair)
    assert np.array_equal(labels, _scipy_labels(points, radius)[0])
