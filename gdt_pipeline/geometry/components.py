"""Connected components of the graph of points closer than a radius, without holding the graph.

scipy's way (``query_pairs`` then ``csgraph.connected_components``) holds every pair several times over: the pair
list (16 B a pair), the matrix's data and its CSR copy, about 50 B a pair. The fusion's segments of a 10 M-point
epoch are 5.5 M pairs there (+320 MB); here the pairs come a piece of points at a time and are merged into a
union-find forest (8 B a point) as they come, so the memory is the forest and one piece's pairs. The forest is
compiled here because scipy's own (``scipy.cluster.hierarchy.DisjointSet``) merges one pair per Python call.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..compiled import njit

# about this many pairs are listed at a time (24 B each in scipy's sparse-distance output: 12 MB a piece)
PAIRS_PER_PIECE = 500_000


def radius_components(tree: cKDTree, radius: float, pairs_per_piece: int = PAIRS_PER_PIECE,
                      listed: int | None = None) -> np.ndarray:
    """Per point of ``tree``, the label of its component in the graph of points at most ``radius`` apart; labels
    are numbered 0, 1, ... in the order of each component's lowest point (as scipy's ``connected_components``).
    ``listed``: the ordered pairs within ``radius`` (``check_radius``'s count), when the caller has counted them."""
    n = int(tree.n)
    parent = np.arange(n, dtype=np.int64)
    if n == 0:
        return parent
    # pieces of about equal pairs where the density is even, compact in space since cut along the tree's own order
    # (a piece's pairs cost what they are against the whole tree); ordered pairs, both ways, each point with itself
    listed = max(int(tree.count_neighbors(tree, radius)) if listed is None else listed, 1)
    per_piece = max(1, int(n * min(1.0, pairs_per_piece / listed)))
    for start in range(0, n, per_piece):
        part = tree.indices[start:start + per_piece]
        pairs = cKDTree(tree.data[part]).sparse_distance_matrix(tree, radius, output_type="ndarray")
        _union_pairs(parent, part[pairs["i"]], np.ascontiguousarray(pairs["j"]))
    return _labels(parent)


@njit(cache=True)
def _root(parent: np.ndarray, x: int) -> int:
    root = x
    while parent[root] != root:
        root = parent[root]
    while parent[x] != root:  # path compression: later finds are one step
        parent[x], x = root, parent[x]
    return root


@njit(cache=True)
def _union_pairs(parent: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    # the lower root wins, so that every component's root is its lowest point
    for k in range(len(a)):
        ra, rb = _root(parent, a[k]), _root(parent, b[k])
        if ra < rb:
            parent[rb] = ra
        elif rb < ra:
            parent[ra] = rb


@njit(cache=True)
def _labels(parent: np.ndarray) -> np.ndarray:
    label = np.empty(len(parent), np.int64)
    count = 0
    for i in range(len(parent)):
        r = _root(parent, i)
        if r == i:
            label[i] = count
            count += 1
        else:
            label[i] = label[r]  # r < i: labelled already
    return label
