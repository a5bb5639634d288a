"""Ray casting through Open3D: crossings listed per ray, and no call that Open3D cannot take (zero rays)."""

from __future__ import annotations

import numpy as np
import trimesh

from gdt_pipeline.geometry import line_crossings, list_intersections, raycasting_scene
from gdt_pipeline.region_of_view.occlusion import segment_hits


def _box_scene() -> tuple[object, list[np.ndarray]]:
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    return raycasting_scene([box]), [np.asarray(box.face_normals)]


def test_lines_cross_a_box_twice_each_and_no_lines_cross_nothing() -> None:
    """A vertical line through a unit box crosses its top and bottom within reach, at ±0.5 of the point; zero lines
    (a tile whose crop casts none) give empty results, not Open3D's segfault on zero rays."""
    scene, normals = _box_scene()
    pts = np.array([[0.1, 0.2, 0.0], [-0.3, 0.0, 0.25]])
    axis = np.tile([0.0, 0.0, 1.0], (2, 1))
    ray, along, n = line_crossings(scene, normals, pts, axis, np.full(2, 2.0))
    assert np.array_equal(np.sort(ray), [0, 0, 1, 1])
    np.testing.assert_allclose(np.sort(along[ray == 0]), [-0.5, 0.5], atol=1e-6)
    np.testing.assert_allclose(np.sort(along[ray == 1]), [-0.25, 0.75], atol=1e-6)
    np.testing.assert_allclose(np.abs(n[:, 2]), 1.0)
    ray, along, n = line_crossings(scene, normals, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    assert ray.shape == (0,) and along.shape == (0,) and n.shape == (0, 3)
    hits, prims = segment_hits(scene, np.zeros((0, 3)), np.zeros((0, 3)))
    assert hits.shape == (0,) and prims.shape == (0,)
    empty = list_intersections(scene, np.zeros((0, 6), dtype=np.float32))
    assert empty["ray_splits"].tolist() == [0] and len(empty["t_hit"]) == 0

