"""Uncertainty-directed correspondences on hand-built cases: the ray along a point's beam finds the right facet
where the closest point picks a wrong one; facets of a shifted mesh are flagged and those of an unchanged one are
not; point-to-point mixtures; no correspondence means new; the same seed gives the same result."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh

from gdt_pipeline import (
    Composite,
    CompositeItem,
    Dataset,
    EpochInfo,
    GaussianUncertainty,
    StageContext,
)


def _item(key: str, ds: Dataset) -> CompositeItem:
    n = ds.n_elements
    return CompositeItem(key, ds, "E0", np.zeros(n), np.full(n, np.nan), np.zeros(n), np.ones(n, bool))


def _run(registry, name: str, params: dict, slots: dict, seed: int = 0) -> dict:
    spec = registry.get(name)
    ctx = StageContext(stage=spec, params=spec.params.model_validate(params), slots=slots,
                       epoch=EpochInfo("E1", 1, "as-is", seed, Path("."), "m"), rng=np.random.default_rng(seed),
                       seed=seed, log=logging.getLogger("test"))
    return spec.run(ctx)


def _chain(registry, corr_stage: str, recent: list[Dataset], comp: Composite, tau: float = 4.0, seed: int = 0,
           params: dict | None = None, calibrated: float | None = None):
    slots = {"recent": recent, "reference": comp}
    corr = _run(registry, corr_stage, params or {}, slots, seed)["correspondences"]
    scores = _run(registry, "bhattacharyya", {"samples": 512}, {**slots, "correspondences": corr}, seed)["scores"]
    if calibrated is None:
        change = _run(registry, "fixed", {"tau": tau}, {"scores": scores})["change"]
    else:
        change = _run(registry, "calibrated_threshold", {"false_alarm": calibrated, "samples": 4000},
                      {"scores": scores}, seed)["change"]
    return corr, scores, change


def _beam_scene():
    """A floor facet A (z = 0) and a short wall facet B that is closer to the measured point than A is."""
    sigma_b, sigma_l = 0.01, 0.001
    d = np.array([np.sin(np.radians(60)), 0.0, -np.cos(np.radians(60))])  # the beam, 60° off the floor normal
    truth = np.zeros(3)
    q = truth - 3 * sigma_b * d  # measured 3 sigma short of the floor along the beam
    floor = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0]], float)
    wall_x = q[0] - 0.01
    top = q[2] - 0.001  # the wall stays below the point, so the backward ray misses it
    wall = np.array([[wall_x, -0.5, -0.05], [wall_x, 0.5, -0.05], [wall_x, 0.0, top]], float)
    verts = np.vstack([floor, wall])
    mesh = Dataset("cad", "as-designed", verts, faces=[[0, 1, 2], [3, 4, 5]],
                   uncertainty=GaussianUncertainty.isotropic(0.001))
    cov = sigma_b**2 * np.outer(d, d) + sigma_l**2 * (np.eye(3) - np.outer(d, d))
    point = Dataset("scan", "as-is", q[None], uncertainty=GaussianUncertainty(cov[None]))
    return mesh, point


def test_ray_along_the_beam_finds_the_right_facet(registry) -> None:
    mesh, point = _beam_scene()
    comp = Composite((_item("E0_cad", mesh),))
    # the closest point picks the wall (facet 1), and the pair looks changed
    corr, near_scores, change = _chain(registry, "nearest", [point], comp)
    assert corr[0].ref_element[near_scores[0].match[0]] == 1
    assert change[0].mask[0]
    # the uncertainty-directed search also tries the ray along the beam: the floor (facet 0) wins, unchanged
    corr, scores, change = _chain(registry, "point_to_mesh", [point], comp)
    c = corr[0]
    assert set(c.ref_element.tolist()) == {0, 1}  # both candidates were considered
    best = scores[0].match[0]
    assert c.ref_element[best] == 0
    np.testing.assert_allclose(c.position[best], [0.0, 0.0, 0.0], atol=1e-6)  # the true spot on the floor
    # BD of a 3 sigma offset along the beam: (3²·σ_b²/((σ_b²+σ_r²)/2))/8 + ½ ln(det ratio) = 2.23 + 0.81
    assert scores[0].score[0] == pytest.approx(3.04, abs=0.01) and scores[0].score[0] < near_scores[0].score[0]
    assert not change[0].mask[0]


def test_shifted_mesh_facets_are_flagged_unchanged_ones_not(registry) -> None:
    a = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    b = trimesh.creation.box(extents=(0.3, 0.3, 0.3))
    b.apply_translation((1.0, 0.0, 0.0))
    tol = GaussianUncertainty.isotropic(0.001)
    comp = Composite((_item("E0_a", Dataset("a", "as-designed", a.vertices, faces=a.faces, uncertainty=tol)),
                      _item("E0_b", Dataset("b", "as-designed", b.vertices, faces=b.faces, uncertainty=tol))))
    # the scan's meshes: a re-triangulated (subdivided) but unchanged; b subdivided and shifted 2 cm along x
    a2, b2 = a.subdivide(), b.subdivide().subdivide()
    b2.apply_translation((0.02, 0.0, 0.0))
    scan_unc = GaussianUncertainty.isotropic(0.002)
    recent = [Dataset("a_scan", "as-is", a2.vertices, faces=a2.faces, uncertainty=scan_unc),
              Dataset("b_scan", "as-is", b2.vertices, faces=b2.faces, uncertainty=scan_unc)]
    corr, scores, change = _chain(registry, "mesh_to_mesh", recent, comp, params={"sample_density": 400})
    assert not change[0].mask.any()  # every facet of the unchanged mesh
    # the +x face left its plane by 2 cm and lies outside the old box (the -x face now cuts through the old
    # box's side faces, so its edge facets rightly touch old surface)
    moved_off = b2.face_normals[:, 0] > 0.99
    assert change[1].mask[moved_off].all()
    cx = b2.triangles_center[:, 0]
    slid = ~moved_off & (cx > b.bounds[0][0] + 0.04) & (cx < b.bounds[1][0] - 0.02)  # slid within their planes
    assert slid.sum() > 20 and not change[1].mask[slid].any()
    assert len(corr[0].element) > 2 * recent[0].n_elements  # several samples per facet
    c, s = corr[0], scores[0]
    assert np.all(s.score[c.element[s.match]] == s.score)  # the facet keeps the lowest score of its samples


def test_point_to_point_mixtures_and_no_correspondence(registry) -> None:
    rng = np.random.default_rng(3)
    sigma = 0.003
    # dense enough that every query has neighbours in its 99 % ellipsoid (about 12 expected)
    truth_ref = np.column_stack([rng.uniform(0, 1, (20_000, 2)), np.zeros(20_000)])
    truth_new = np.column_stack([rng.uniform(0, 1, (2000, 2)), np.zeros(2000)])
    ref = Dataset("ref", "as-is", truth_ref + rng.normal(0, sigma, truth_ref.shape),
                  uncertainty=GaussianUncertainty.isotropic(sigma))
    comp = Composite((_item("E0_ref", ref),))
    above = np.column_stack([rng.uniform(0.2, 0.8, (100, 2)), np.full(100, 0.05)])  # 5 cm above: new
    pts = np.vstack([truth_new + rng.normal(0, sigma, truth_new.shape), above])
    recent = Dataset("scan", "as-is", pts, uncertainty=GaussianUncertainty.isotropic(sigma))
    corr, scores, change = _chain(registry, "point_to_point", [recent], comp, calibrated=0.01)
    c = corr[0]
    assert c.ref_uncertainty is not None and c.ref_uncertainty.model == "mixture"
    assert c.ref_uncertainty.weights.shape[1] > 1  # several neighbours merged
    assert not np.any(np.isin(np.arange(2000, 2100), c.element))  # nothing within the 99 % ellipsoid
    assert np.all(np.isnan(scores[0].score[2000:])) and change[0].mask[2000:].all()  # so: new, not dropped
    assert change[0].mask[:2000].mean() < 0.03  # the unchanged surface stays (nearly all) unchanged


def test_mesh_to_point_and_auto(registry) -> None:
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    rng = np.random.default_rng(0)
    cloud = trimesh.sample.sample_surface(box, 20_000, seed=1)[0] + rng.normal(0, 0.001, (20_000, 3))
    comp = Composite((_item("E0_cloud", Dataset("cloud", "as-is", cloud,
                                                uncertainty=GaussianUncertainty.isotropic(0.001))),))
    mesh = Dataset("cad", "as-designed", box.vertices, faces=box.faces,
                   uncertainty=GaussianUncertainty.isotropic(0.002))
    corr, _, change = _chain(registry, "mesh_to_point", [mesh], comp, params={"sample_density": 2000})
    assert not change[0].mask.any()
    with pytest.raises(ValueError, match="use mesh_to_point or auto"):
        _run(registry, "point_to_point", {}, {"recent": [mesh], "reference": comp})
    # auto on a twin holding both a cloud and a mesh, with a point query: both kinds of candidates
    shifted = box.vertices + np.array([2.0, 0.0, 0.0])
    both = Composite((comp.items[0], _item("E0_cad", Dataset("cad", "as-designed", shifted,
                                                             faces=box.faces,
                                                             uncertainty=GaussianUncertainty.isotropic(0.001)))))
    q = Dataset("q", "as-is", np.array([[0.2, 0.0, 0.0], [2.2, 0.0, 0.0]]),
                uncertainty=GaussianUncertainty.isotropic(0.002))
    corr, _, change = _chain(registry, "auto", [q], both)
    c = corr[0]
    assert set(c.ref_item[c.element == 0].tolist()) == {0} and set(c.ref_item[c.element == 1].tolist()) == {1}
    assert not change[0].mask.any()


def test_same_seed_same_result(registry) -> None:
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    comp = Composite((_item("E0_b", Dataset("b", "as-designed", box.vertices, faces=box.faces,
                                            uncertainty=GaussianUncertainty.isotropic(0.001))),))
    moved = box.vertices + 0.001
    recent = [Dataset("s", "as-is", moved, faces=box.faces, uncertainty=GaussianUncertainty.isotropic(0.002))]
    runs = [_chain(registry, "mesh_to_mesh", recent, comp, seed=s, params={"sample_density": 300})
            for s in (7, 7, 8)]
    (c1, s1, _), (c2, s2, _), (c3, _, _) = runs
    assert np.array_equal(c1[0].query_position, c2[0].query_position)
    assert np.array_equal(s1[0].score, s2[0].score, equal_nan=True)
    assert not np.array_equal(c1[0].query_position, c3[0].query_position)
