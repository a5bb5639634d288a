"""COPC files for tests and benchmarks, written through copc-lib (``copclib`` on PyPI): laspy reads COPC but cannot
write it, and PDAL's writer is not packaged for this machine's Debian.

The octree is built the way COPC writers do (untwine, PDAL): top down, each node keeps up to ``node_points`` of the
points falling in its cube, drawn at random, and hands the rest to its eight children; the deepest level keeps
all. Every node with points below it thus has points itself, which is what a reader's traversal from the root needs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

NODE_POINTS = 50_000
MAX_DEPTH = 12


def _levels(points: np.ndarray, corner: np.ndarray, cube: float, node_points: int, rng: np.random.Generator
            ) -> tuple[np.ndarray, np.ndarray]:
    """Per point its octree level and its cell at that level, top down (vectorised per level)."""
    n = len(points)
    level = np.full(n, -1, np.int64)
    cells = np.zeros((n, 3), np.int64)
    priority = rng.permutation(n)
    todo = np.arange(n)
    for depth in range(MAX_DEPTH + 1):
        ijk = np.minimum(np.floor((points[todo] - corner) / cube * 2 ** depth).astype(np.int64), 2 ** depth - 1)
        if depth == MAX_DEPTH:
            level[todo], cells[todo] = depth, ijk
            break
        key = (ijk[:, 0] << 40) | (ijk[:, 1] << 20) | ijk[:, 2]
        order = np.lexsort((priority[todo], key))
        sorted_key = key[order]
        starts = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
        rank = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
        stay = np.zeros(len(todo), bool)
        stay[order[rank < node_points]] = True
        level[todo[stay]], cells[todo[stay]] = depth, ijk[stay]
        todo = todo[~stay]
        if len(todo) == 0:
            break
    return level, cells


def write_copc(path: Path, points: np.ndarray, *, scale: float = 0.0001, classification: np.ndarray | None = None,
               intensity: np.ndarray | None = None, node_points: int = NODE_POINTS, seed: int = 0) -> Path:
    """Write ``points`` (and their ASPRS classes and intensities) as a COPC file (point format 6)."""
    import copclib
    import laspy

    points = np.asarray(points, np.float64)
    lower, upper = points.min(axis=0), points.max(axis=0)
    offset = np.floor(lower / scale) * scale
    fmt = laspy.PointFormat(6)
    records = laspy.ScaleAwarePointRecord.zeros(len(points), point_format=fmt, scales=np.full(3, scale),
                                                offsets=offset)
    records.x, records.y, records.z = points[:, 0], points[:, 1], points[:, 2]
    if classification is not None:
        records.classification = np.asarray(classification, np.uint8)
    if intensity is not None:
        records.intensity = np.asarray(intensity, np.uint16)
    # the stored (quantised) coordinates decide the cubes, as a reader sees them
    stored = np.column_stack([np.asarray(records.x), np.asarray(records.y), np.asarray(records.z)])
    lower, upper = stored.min(axis=0), stored.max(axis=0)
    centre, half = (lower + upper) / 2, float(np.max(upper - lower)) / 2 * (1 + 1e-6) + scale
    level, cells = _levels(stored, centre - half, 2 * half, node_points, np.random.default_rng(seed))
    config = copclib.CopcConfigWriter(6, copclib.Vector3(scale, scale, scale), copclib.Vector3(*map(float, offset)))
    config.las_header.min = copclib.Vector3(*map(float, lower))
    config.las_header.max = copclib.Vector3(*map(float, upper))
    info = config.copc_info
    info.center_x, info.center_y, info.center_z = map(float, centre)
    info.halfsize, info.spacing = half, 2 * half / 128
    order = np.lexsort((cells[:, 2], cells[:, 1], cells[:, 0], level))
    keys = np.column_stack([level, cells])[order]
    starts = np.flatnonzero(np.r_[True, np.any(keys[1:] != keys[:-1], axis=1)])
    raw = records.array[order]
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = copclib.FileWriter(str(path), config)
    try:
        for s, e in zip(starts, np.r_[starts[1:], len(order)], strict=True):
            d, x, y, z = (int(v) for v in keys[s])
            writer.AddNode(copclib.VoxelKey(d, x, y, z), copclib.VectorChar(np.frombuffer(raw[s:e].tobytes(), np.int8)))
    finally:
        writer.Close()
    return path
