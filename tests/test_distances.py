"""Distance measures and thresholds: every Bhattacharyya form against independent numerical integration (1e-6
relative), symmetry, BD = 0 for identical distributions, Hotelling and Welch against scipy, the calibrated threshold's
false-alarm rate on simulated unchanged data, and p-values through to the twin."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from scipy import integrate
from scipy.spatial import ConvexHull, HalfspaceIntersection
from scipy.spatial.transform import Rotation
from scipy.stats import chi2, multivariate_normal

from gdt_pipeline import (
    BoxUncertainty,
    Composite,
    CompositeItem,
    Correspondences,
    Dataset,
    EpochInfo,
    GaussianUncertainty,
    MixtureUncertainty,
    StageContext,
)
from stages.distance.bhattacharyya_maths import (
    bc_box_box,
    bc_gauss_box,
    bc_gauss_mixture,
    bc_importance,
    bd_gauss_gauss,
    bhattacharyya,
)

R1 = Rotation.from_euler("xyz", [0.3, 0.5, -0.8]).as_matrix()
R2 = Rotation.from_euler("zyx", [1.1, -0.2, 0.4]).as_matrix()
H = np.array([0.002, 0.0015, 0.001])


def _nquad_gauss_box(mu, cov, h, rot=None) -> float:
    """∫_box √(N(x) / V) dx by adaptive cubature in the box's frame."""
    rot = np.eye(3) if rot is None else rot
    mvn = multivariate_normal(mu, cov)
    vol = np.prod(2 * h)

    def f(z, y, x):
        return np.sqrt(mvn.pdf(rot @ np.array([x, y, z])) / vol)

    val, _ = integrate.nquad(f, [[-h[2], h[2]], [-h[1], h[1]], [-h[0], h[0]]],
                             opts={"epsabs": 1e-12, "epsrel": 1e-10})
    return val


GB_CASES = {
    "aligned": (np.array([0.0011, -0.0004, 0.0003]), np.diag([4e-6, 1e-6, 2.5e-7]), None),
    "turned, anisotropic 4:1": (np.array([0.0011, -0.0004, 0.0003]), R1 @ np.diag([4e-6, 1e-6, 2.5e-7]) @ R1.T, None),
    "turned box, near-singular 50:1": (np.array([-0.0005, 0.0002, 0.0]), R1 @ np.diag([1e-6, 1e-6, 4e-10]) @ R1.T, R2),
}


@pytest.mark.parametrize("case", list(GB_CASES))
def test_gaussian_box_against_cubature(case: str) -> None:
    mu, cov, rot = GB_CASES[case]
    box = BoxUncertainty(H[None], None if rot is None else rot[None])
    bc, err = bc_gauss_box(mu[None], cov[None], np.zeros((1, 3)), box, eps=1e-9)
    want = _nquad_gauss_box(mu, cov, H, rot)
    assert bc[0] == pytest.approx(want, rel=1e-6)
    assert err[0] <= 1e-9
    # symmetry: the same pair the other way round
    bd_ab, _, _ = bhattacharyya(mu[None], GaussianUncertainty(cov[None]), np.zeros((1, 3)), box,
                                rng=np.random.default_rng(0), eps=1e-9)
    bd_ba, _, _ = bhattacharyya(np.zeros((1, 3)), box, mu[None], GaussianUncertainty(cov[None]),
                                rng=np.random.default_rng(0), eps=1e-9)
    assert bd_ab[0] == pytest.approx(bd_ba[0], rel=1e-12) and bd_ab[0] == pytest.approx(-np.log(want), rel=1e-6)


def _box_halfspaces(center, h, rot) -> np.ndarray:
    rows = []
    for i in range(3):
        a = rot[:, i]
        rows += [np.r_[a, -(a @ center + h[i])], np.r_[-a, (a @ center - h[i])]]
    return np.array(rows)


def _overlap_volume(c1, h1, r1, c2, h2, r2) -> float:
    """Exact intersection volume of two oriented boxes: half-space intersection and its convex hull."""
    hs = np.vstack([_box_halfspaces(c1, h1, r1), _box_halfspaces(c2, h2, r2)])
    try:
        inter = HalfspaceIntersection(hs, (c1 + c2) / 2)
    except Exception:
        return 0.0
    return ConvexHull(inter.intersections).volume


def test_box_box_aligned_against_exact_polytope_volume() -> None:
    h2 = np.array([0.001, 0.002, 0.0012])
    c2 = np.array([0.0007, -0.0005, 0.0004])
    for rot in (np.eye(3), R1):
        b1, b2 = BoxUncertainty(H[None], rot[None]), BoxUncertainty(h2[None], rot[None])
        bc, _ = bc_box_box(np.zeros((1, 3)), b1, c2[None], b2)
        vol = _overlap_volume(np.zeros(3), H, rot, c2, h2, rot)
        assert bc[0] == pytest.approx(vol / np.sqrt(np.prod(2 * H) * np.prod(2 * h2)), rel=1e-9)
    same, _ = bc_box_box(np.zeros((1, 3)), b1, np.zeros((1, 3)), b1)
    assert same[0] == pytest.approx(1.0)  # BD = 0 for identical distributions


def test_turned_box_pair_and_mixtures_by_importance_sampling() -> None:
    rng = np.random.default_rng(3)
    h2 = np.array([0.001, 0.002, 0.0012])
    c2 = np.array([0.0007, -0.0005, 0.0004])
    b1, b2 = BoxUncertainty(H[None], R1[None]), BoxUncertainty(h2[None], R2[None])
    bd, err, method = bhattacharyya(np.zeros((1, 3)), b1, c2[None], b2, rng=rng, samples=200_000)
    want = _overlap_volume(np.zeros(3), H, R1, c2, h2, R2) / np.sqrt(np.prod(2 * H) * np.prod(2 * h2))
    assert "importance" in method and abs(np.exp(-bd[0]) - want) <= err[0] and err[0] < 0.01
    # a mixture against a Gaussian: against cubature of √(p1 p2)
    mix = MixtureUncertainty(np.array([[0.6, 0.4]]), np.array([[[0.001, 0, 0], [-0.001, 0.0005, 0]]]),
                             np.array([[np.eye(3) * 1e-6, np.diag([2e-6, 1e-6, 5e-7])]]))
    g = GaussianUncertainty((R1 @ np.diag([3e-6, 1e-6, 1e-6]) @ R1.T)[None])
    mu_g = np.array([0.0005, 0.0, 0.0002])
    bc, se = bc_importance(np.zeros((1, 3)), mix, mu_g[None], g, rng, 400_000)

    # reference: √(p1 p2) on a dense grid (smooth and fast-decaying: the trapezoid rule converges exponentially)
    axis = np.linspace(-0.009, 0.009, 141)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    one = np.zeros(len(grid), dtype=np.int64)
    vals = np.sqrt(mix.take(one).pdf(grid) * g.take(one).pdf(grid - mu_g)).reshape(141, 141, 141)
    want = integrate.trapezoid(integrate.trapezoid(integrate.trapezoid(vals, axis, axis=2), axis, axis=1), axis)
    assert abs(bc[0] - want) <= se[0] and se[0] < 2e-3
    # the bounded Gaussian-mixture sampler: same integral, far fewer samples, and what bhattacharyya() uses
    bc_b, se_b = bc_gauss_mixture(mu_g[None], g.covariance(1), np.zeros((1, 3)), mix, rng, 4096)
    assert abs(bc_b[0] - want) <= se_b[0] and se_b[0] < 4e-3
    bd, err, method = bhattacharyya(np.zeros((1, 3)), mix, mu_g[None], g, rng=rng)
    assert method == "gaussian mixture bound sampling" and abs(np.exp(-bd[0]) - want) <= err[0] < 0.01 * want
    same, se_same = bc_importance(np.zeros((1, 3)), mix, np.zeros((1, 3)), mix, rng, 20_000)
    assert same[0] == pytest.approx(1.0, abs=1e-12) and se_same[0] < 1e-12  # identical: the ratio is exactly 1


def test_gaussian_pairs_vectorised_match_the_matrix_form() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(1000, 3, 3)), rng.normal(size=(1000, 3, 3))
    c1, c2 = a @ np.swapaxes(a, 1, 2) + 1e-3 * np.eye(3), b @ np.swapaxes(b, 1, 2) + 1e-3 * np.eye(3)
    m1, m2 = rng.normal(size=(1000, 3)), rng.normal(size=(1000, 3))
    c = (c1 + c2) / 2
    want = (np.einsum("ni,nij,nj->n", m2 - m1, np.linalg.inv(c), m2 - m1) / 8
            + 0.5 * (np.linalg.slogdet(c)[1] - 0.5 * (np.linalg.slogdet(c1)[1] + np.linalg.slogdet(c2)[1])))
    np.testing.assert_allclose(bd_gauss_gauss(m1, c1, m2, c2), want, rtol=1e-9)


def _pairs_context(registry, stage: str, params: dict, recent: Dataset, reference: Dataset, slots=None):
    n = recent.n_elements
    comp = Composite((CompositeItem("E0_ref", reference, "E0", np.zeros(n), np.full(n, np.nan), np.zeros(n),
                                    np.ones(n, bool)),))
    corr = Correspondences(0, np.zeros(n, np.int64), np.arange(n), reference.points, np.zeros(n))
    spec = registry.get(stage)
    base = {"recent": [recent], "reference": comp, "correspondences": [corr], **(slots or {})}
    ctx = StageContext(stage=spec, params=spec.params.model_validate(params), slots=base,
                       epoch=EpochInfo("E1", 1, "as-is", 5, Path("."), "m"), rng=np.random.default_rng(5), seed=5,
                       log=logging.getLogger("test"))
    return spec.run(ctx), ctx


def _unchanged_pairs(n: int, rng: np.random.Generator, ref_unc, q_unc) -> tuple[Dataset, Dataset]:
    """The same true points measured twice, each measurement off by its own model's error."""
    truth = rng.uniform(-1, 1, (n, 3))
    ref = Dataset("ref", "as-designed", truth + ref_unc.sample(n, rng, 1)[:, 0], uncertainty=ref_unc)
    rec = Dataset("rec", "as-is", truth + q_unc.sample(n, rng, 1)[:, 0], uncertainty=q_unc)
    return rec, ref


@pytest.mark.parametrize("measure,ref_model", [("bhattacharyya", "gaussian"), ("bhattacharyya", "box"),
                                                ("hotelling", "gaussian"), ("welch_m3c2", "gaussian")])
def test_calibrated_threshold_achieves_its_false_alarm_rate(registry, measure: str, ref_model: str) -> None:
    rng = np.random.default_rng(21)
    n = 40_000 if ref_model == "box" else 100_000
    rots = Rotation.random(n, random_state=4).as_matrix()
    q_unc = GaussianUncertainty(rots @ np.diag([4e-4, 1e-4, 2.5e-5]) @ np.swapaxes(rots, 1, 2))
    ref_unc = (GaussianUncertainty.isotropic(0.006) if ref_model == "gaussian"
               else BoxUncertainty(np.array([[0.01, 0.01, 0.01]])))
    rec, ref = _unchanged_pairs(n, rng, ref_unc, q_unc)
    scores, _ = _pairs_context(registry, measure, {}, rec, ref)
    alpha = 0.02
    out, ctx = _pairs_context(registry, "calibrated_threshold", {"false_alarm": alpha, "samples": 100_000}, rec, ref,
                              {"scores": scores["scores"]})
    [change] = out["change"]
    rate = change.mask.mean()
    assert rate == pytest.approx(alpha, rel=0.2), (measure, rate)
    [cal] = ctx.notes["calibration"]
    assert cal["false_alarm_achieved"] == pytest.approx(alpha, rel=0.2) and cal["tau"] == change.threshold


def test_calibrated_threshold_per_epoch_pools_the_datasets(registry) -> None:
    # two scans of one epoch with different noise: one τ for both, and the share of all their unchanged elements
    # flagged is the rate asked for (each scan's own share may differ, which is what pooling trades for speed)
    rng = np.random.default_rng(8)
    alpha = 0.02
    ref_unc = GaussianUncertainty.isotropic(0.004)
    scores = []
    for n, sigma in ((60_000, 0.001), (20_000, 0.01)):
        rec, ref = _unchanged_pairs(n, rng, ref_unc, GaussianUncertainty(np.diag([sigma**2, 1e-6, 1e-6])[None]))
        out, _ = _pairs_context(registry, "bhattacharyya", {}, rec, ref)
        scores += out["scores"]
    out, ctx = _pairs_context(registry, "calibrated_threshold", {"false_alarm": alpha, "samples": 60_000,
                                                                 "per": "epoch"}, rec, ref, {"scores": scores})
    changes = out["change"]
    assert len(changes) == 2 and changes[0].threshold == changes[1].threshold
    flagged = np.concatenate([c.mask for c in changes])
    assert flagged.mean() == pytest.approx(alpha, rel=0.15)
    [cal] = ctx.notes["calibration"]
    assert cal["false_alarm_achieved"] == pytest.approx(alpha, rel=0.15) and cal["tau"] == changes[0].threshold
    per_dataset, _ = _pairs_context(registry, "calibrated_threshold", {"false_alarm": alpha, "samples": 60_000},
                                    rec, ref, {"scores": scores})
    assert per_dataset["change"][0].threshold != per_dataset["change"][1].threshold


def test_hotelling_and_welch_against_scipy(registry) -> None:
    rng = np.random.default_rng(2)
    cov = np.diag([1e-4, 4e-4, 9e-4])
    ref = Dataset("ref", "as-designed", np.zeros((3, 3)), uncertainty=GaussianUncertainty(cov[None]))
    rec = Dataset("rec", "as-is", np.array([[0.01, 0, 0], [0, 0.05, 0], [0.02, 0.02, 0.02]]),
                  uncertainty=GaussianUncertainty(cov[None]))
    out, _ = _pairs_context(registry, "hotelling", {}, rec, ref)
    [s] = out["scores"]
    t2 = np.einsum("ni,ij,nj->n", rec.points, np.linalg.inv(2 * cov), rec.points)
    np.testing.assert_allclose(s.score, t2, rtol=1e-12)
    np.testing.assert_allclose(s.p_value, chi2.sf(t2, 3), rtol=1e-12)
    box_ref = Dataset("ref", "as-designed", np.zeros((3, 3)), uncertainty=BoxUncertainty(np.full((1, 3), 0.01)))
    with pytest.raises(ValueError, match="holds only for normal distributions"):
        _pairs_context(registry, "hotelling", {}, rec, box_ref)
    # welch along a mesh facet's normal: a flat triangle in z = 0, points above it
    tri = Dataset("plane", "as-designed", np.array([[-1, -1, 0], [3, -1, 0], [-1, 3, 0]], float), faces=[[0, 1, 2]],
                  uncertainty=GaussianUncertainty.isotropic(0.002))
    pts = np.column_stack([rng.uniform(0, 0.5, (5, 2)), [0.0, 0.002, -0.004, 0.01, 0.001]])
    q = Dataset("q", "as-is", pts, uncertainty=GaussianUncertainty.isotropic(0.003))
    comp = Composite((CompositeItem("E0_plane", tri, "E0", np.zeros(1), np.full(1, np.nan), np.zeros(1),
                                    np.ones(1, bool)),))
    proj = pts * [1, 1, 0]
    corr = Correspondences(0, np.zeros(5, np.int64), np.zeros(5, np.int64), proj, np.abs(pts[:, 2]))
    spec = registry.get("welch_m3c2")
    ctx = StageContext(stage=spec, params=spec.params(), slots={"recent": [q], "reference": comp,
                                                                "correspondences": [corr]},
                       epoch=EpochInfo("E1", 1, "as-is", 0, Path("."), "m"), rng=rng, seed=0,
                       log=logging.getLogger("t"))
    [w] = spec.run(ctx)["scores"]
    t = np.abs(pts[:, 2]) / np.sqrt(0.002**2 + 0.003**2)
    np.testing.assert_allclose(w.score, t, rtol=1e-9)
    from scipy.stats import norm

    np.testing.assert_allclose(w.p_value, 2 * norm.sf(t), rtol=1e-9)


def test_tolerance_multiple_and_significance(registry) -> None:
    rng = np.random.default_rng(1)
    rec, ref = _unchanged_pairs(1000, rng, GaussianUncertainty.isotropic(0.01), GaussianUncertainty.isotropic(0.01))
    scores, sctx = _pairs_context(registry, "bhattacharyya", {"epsilon": 1e-4}, rec, ref)
    assert scores["scores"][0].tolerance == 1e-4 and sctx.notes["methods"] == ["closed form"]
    out, _ = _pairs_context(registry, "tolerance_multiple", {"k": 5000}, rec, ref, {"scores": scores["scores"]})
    assert out["change"][0].threshold == pytest.approx(0.5)
    hot, _ = _pairs_context(registry, "hotelling", {}, rec, ref)
    out, _ = _pairs_context(registry, "significance", {"alpha": 0.05}, rec, ref, {"scores": hot["scores"]})
    assert np.array_equal(out["change"][0].mask, hot["scores"][0].p_value < 0.05)
    assert out["change"][0].mask.mean() == pytest.approx(0.05, abs=0.025)
    with pytest.raises(ValueError, match="gives no p-values"):
        _pairs_context(registry, "significance", {}, rec, ref, {"scores": scores["scores"]})


def test_p_values_reach_the_twin(cube_scene, registry) -> None:
    from pxr import Usd, UsdGeom

    from gdt_pipeline.runner import run_workflow

    from .conftest import write_cube_workflow

    wf = write_cube_workflow(cube_scene)
    wf.write_text(wf.read_text().replace("uses: bhattacharyya", "uses: hotelling")
                  .replace("  - uses: fixed\n    role: as-is\n    with: {tau: 10.0}\n",
                           "  - uses: significance\n    role: as-is\n    with: {alpha: 0.001}\n"))
    twin = run_workflow(wf, registry=registry).twin
    stage = Usd.Stage.Open(str(twin / "twin.usda"))  # keep the stage alive while its prims are read
    pv = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Twin/E1_scan"))
    p = np.asarray(pv.GetPrimvar("gdt:pValue").Get())
    score = np.asarray(pv.GetPrimvar("gdt:changeScore").Get())
    state = np.asarray(pv.GetPrimvar("gdt:changeState").Get())
    np.testing.assert_allclose(p, chi2.sf(score, 3).astype(np.float32), rtol=1e-4, atol=1e-30)
    assert np.array_equal(state == 1, ~(p >= 0.001))
    tp = np.sum((state == 1) & cube_scene.changed)
    assert 2 * tp / (np.sum(state == 1) + cube_scene.changed.sum()) > 0.95


def test_gaussian_mixture_bound_holds_for_very_different_precisions() -> None:
    """A 0.1 mm query against a mixture of 5 cm ToF neighbours: the bound sampler against a dense-grid integral."""
    rng = np.random.default_rng(11)
    means = np.array([[[0.0, 0.0, 0.0], [0.01, 0.004, 0.0], [-0.006, 0.0, 0.012]]])
    covs = np.array([[np.diag([0.05, 0.01, 0.01]) ** 2] * 3])
    mix = MixtureUncertainty(np.array([[0.5, 0.3, 0.2]]), means, covs)
    cq = np.eye(3)[None] * 1e-4 ** 2
    mu_q = np.array([[0.002, 0.001, -0.001]])
    bc, se = bc_gauss_mixture(mu_q, cq, np.zeros((1, 3)), mix, rng, 64)
    # √(p q) is as narrow as p (σ√2 = 0.14 mm), and q is flat on that scale: integrate on a grid around μ_q
    axis = np.linspace(-1e-3, 1e-3, 161)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + mu_q
    one = np.zeros(len(grid), dtype=np.int64)
    vals = np.sqrt(mix.take(one).pdf(grid) * GaussianUncertainty(cq).take(one).pdf(grid - mu_q)).reshape(161, 161,
                                                                                                         161)
    want = integrate.trapezoid(integrate.trapezoid(integrate.trapezoid(vals, axis, axis=2), axis, axis=1), axis)
    assert abs(bc[0] - want) <= max(se[0], 1e-12) and se[0] < 1e-3 * want

