"""A spatial subsample of points fed chunk by chunk: one point per occupied voxel and layer, in bounded memory.

A layer is what the 3-D view draws as one trace (a change state and the epoch that supplied the points). Each voxel
keeps the first point fed into it, so the result depends only on the points and their order: the same twin gives
the same page. While points come in, at most ``hold`` are kept: past that the voxels grow until half of that
remain. At the end the voxel size is the smallest (to 1.1 %) whose occupied voxels fit the budget, on one
grid for the whole twin. Voxel keys are int64 (three 21-bit indices); a count costs 9 bytes a kept point and a
selection 24, computed chunk by chunk, so the working memory is a small multiple of what is kept.

Not Open3D's ``voxel_down_sample``: it needs every point at once (the report reads a twin set by set within 200 MB),
averages the points of a voxel into one that was never measured, and cannot aim at a point budget.
"""

from __future__ import annotations

from collections.abc import Hashable

import numpy as np

AXIS_BITS = 21  # voxel index bits per axis: three fit one int64 key
CHUNK = 1 << 18  # points keyed at once: the float temporaries of a chunk stay a few MB whatever the set's size
SEARCH_STEPS = 6  # bisection steps of the final voxel size on a log scale: from a factor 2 to 1.1 %
MIN_GROWTH = 1.05  # smallest step of the voxel size while coarsening: lands within 5 % of the target


def voxel_keys(xyz: np.ndarray, lower: np.ndarray, size: float) -> np.ndarray:
    """The int64 key of the voxel of edge ``size`` (grid from ``lower``) holding each point."""
    keys = np.empty(len(xyz), dtype=np.int64)
    top = (1 << AXIS_BITS) - 1
    for start in range(0, len(xyz), CHUNK):
        ijk = np.floor((xyz[start:start + CHUNK] - lower) / np.float32(size)).astype(np.int64)
        np.clip(ijk, 0, top, out=ijk)
        keys[start:start + CHUNK] = (ijk[:, 0] << (2 * AXIS_BITS)) | (ijk[:, 1] << AXIS_BITS) | ijk[:, 2]
    return keys


def count_voxels(xyz: np.ndarray, lower: np.ndarray, size: float) -> int:
    """How many voxels of edge ``size`` the points occupy."""
    if len(xyz) == 0:
        return 0
    keys = voxel_keys(xyz, lower, size)
    keys.sort()
    return 1 + int(np.count_nonzero(keys[1:] != keys[:-1]))


def first_per_voxel(xyz: np.ndarray, lower: np.ndarray, size: float) -> np.ndarray:
    """Sorted indices of the first point of ``xyz`` in each occupied voxel of edge ``size``."""
    keys = voxel_keys(xyz, lower, size)
    order = np.argsort(keys, kind="stable")  # stable: within a voxel the earliest point comes first
    keys = keys[order]
    first = np.ones(len(keys), dtype=bool)
    first[1:] = keys[1:] != keys[:-1]
    return np.sort(order[first])


class VoxelSampler:
    """One point per occupied voxel and layer over points fed in any number of chunks (see the module docstring).

    ``lower``/``upper`` bound every point that will be fed (float32 coordinates, as fed)."""

    def __init__(self, budget: int, lower: np.ndarray, upper: np.ndarray, hold: int | None = None) -> None:
        self.budget = max(int(budget), 0)
        # held while feeding: past it the voxels grow until half of it (the budget, by default) remain, in steps
        # of at most 5 %, so that the page shows close to the budget, not far below
        self.hold = max(int(hold or 2 * self.budget), self.budget, 1)
        self.lower = np.asarray(lower, dtype=np.float32)
        self.extent = max(float(np.max(np.asarray(upper, np.float64) - np.asarray(lower, np.float64))), 1e-9)
        self.min_size = self.extent / ((1 << AXIS_BITS) - 2)  # finer voxels would overflow the key
        self.size = 0.0  # 0: nothing reduced yet, every point fed is kept
        self._kept: dict[Hashable, list[np.ndarray]] = {}
        self._count = 0

    def add(self, layer: Hashable, xyz: np.ndarray) -> None:
        """Feed points (N,3) float32 of one layer."""
        xyz = np.asarray(xyz, dtype=np.float32)
        for start in range(0, len(xyz), CHUNK):
            part = xyz[start:start + CHUNK]
            if self.size > 0:
                part = part[first_per_voxel(part, self.lower, self.size)]
            # a copy where it is a view: never keep the caller's array alive through a slice of it
            self._kept.setdefault(layer, []).append(part if part.flags.owndata else part.copy())
            self._count += len(part)
            if self._count > self.hold:
                self._coarsen()

    def _consolidate(self) -> dict[Hashable, np.ndarray]:
        """Each layer's chunks as one array (one layer at a time, so only one is ever held twice)."""
        for layer, parts in self._kept.items():
            if len(parts) > 1:
                self._kept[layer] = [np.concatenate(parts)]
        return {layer: parts[0] for layer, parts in self._kept.items()}

    def _count_at(self, layers: dict[Hashable, np.ndarray], size: float) -> int:
        return sum(count_voxels(xyz, self.lower, size) for xyz in layers.values())

    def _reduce(self, layers: dict[Hashable, np.ndarray], size: float) -> dict[Hashable, np.ndarray]:
        return {layer: xyz[first_per_voxel(xyz, self.lower, size)] for layer, xyz in layers.items()}

    def _coarsen(self) -> None:
        """Grow the voxels until at most half of ``hold`` points are kept."""
        layers = self._consolidate()
        target = max(self.hold // 2, 1)
        # start below the size that would fit a surface; the count falls at most with the cube of the voxel size
        # (a volume), so steps by the cube root of the excess approach the target from above without passing it
        size = max(self.size, self.min_size, self.extent / np.sqrt(target) / 8)
        count = self._count_at(layers, size)
        while count > target:
            size *= max(MIN_GROWTH, float(np.cbrt(count / target)))
            count = self._count_at(layers, size)
        self.size = size
        self._kept = {layer: [xyz] for layer, xyz in self._reduce(layers, size).items()}
        self._count = count

    def result(self) -> tuple[dict[Hashable, np.ndarray], float]:
        """Per layer the points kept, at most ``budget`` in all, and the voxel size used (0: every point kept)."""
        layers = self._consolidate()
        if self.size == 0 and self._count <= self.budget:
            return layers, 0.0
        if self.budget == 0:
            return {layer: xyz[:0] for layer, xyz in layers.items()}, self.extent
        lo = max(self.size, self.min_size)
        if self._count_at(layers, lo) <= self.budget:
            return self._reduce(layers, lo), lo
        hi = lo * 2
        while self._count_at(layers, hi) > self.budget:
            lo, hi = hi, hi * 2
        for _ in range(SEARCH_STEPS):  # the smallest size that fits, to within a factor 2 ** (1 / 64)
            mid = float(np.sqrt(lo * hi))
            lo, hi = (lo, mid) if self._count_at(layers, mid) <= self.budget else (mid, hi)
        return self._reduce(layers, hi), hi
