"""The example plugin gdt-c2c, rebuilt on the public measures API: one cloud-to-cloud implementation (its scores
are the built-in euclidean's), and a null simulator, so calibrated_threshold takes it and meets its false-alarm rate
on real unchanged pairs while it finds the changed ones."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from gdt_pipeline import (
    Composite,
    CompositeItem,
    Correspondences,
    Dataset,
    EpochInfo,
    GaussianUncertainty,
    StageContext,
)

from .conftest import write_cube_workflow


def _run(registry, name: str, params: dict, slots: dict, seed: int = 3) -> tuple[dict, StageContext]:
    spec = registry.get(name)
    ctx = StageContext(stage=spec, params=spec.params.model_validate(params), slots=slots,
                       epoch=EpochInfo("E1", 1, "as-is", seed, Path("."), "m"), rng=np.random.default_rng(seed),
                       seed=seed, log=logging.getLogger("test"))
    return spec.run(ctx), ctx


def _paired_scene(n: int, n_changed: int, rng: np.random.Generator) -> tuple[dict, np.ndarray]:
    """The same true points measured twice (each off by its own model's error); the last ``n_changed`` moved 5 cm."""
    ref_unc, q_unc = GaussianUncertainty.isotropic(0.004), GaussianUncertainty(np.diag([1e-5, 4e-6, 1e-6])[None])
    truth = rng.uniform(-1, 1, (n, 3))
    changed = np.arange(n) >= n - n_changed
    ref = Dataset("ref", "as-designed", truth + ref_unc.sample(n, rng, 1)[:, 0], uncertainty=ref_unc)
    moved = truth + np.where(changed[:, None], [0.05, 0.0, 0.0], 0.0)
    rec = Dataset("rec", "as-is", moved + q_unc.sample(n, rng, 1)[:, 0], uncertainty=q_unc)
    comp = Composite((CompositeItem("E0_ref", ref, "E0", np.zeros(n), np.full(n, np.nan), np.zeros(n),
                                    np.ones(n, bool)),))
    corr = Correspondences(0, np.zeros(n, np.int64), np.arange(n), ref.points, np.zeros(n))
    return {"recent": [rec], "reference": comp, "correspondences": [corr]}, changed


def test_c2c_is_the_builtin_euclidean_and_calibrates(registry) -> None:
    assert registry.get("c2c").version == "0.2.0"
    slots, changed = _paired_scene(60_000, 2_000, np.random.default_rng(4))
    c2c, _ = _run(registry, "c2c", {"scale": 100.0}, slots)
    euc, _ = _run(registry, "euclidean", {"scale": 100.0}, slots)
    [s], [e] = c2c["scores"], euc["scores"]
    rec, ref = slots["recent"][0], slots["reference"].items[0].dataset
    np.testing.assert_array_equal(s.score, np.linalg.norm(rec.points - ref.points, axis=1) * 100.0)
    np.testing.assert_array_equal(s.score, e.score)
    assert s.measure == "c2c" and np.array_equal(s.match, np.arange(len(rec.points)))
    # the null simulator draws from the two actual models: same draws as euclidean's, same scores
    np.testing.assert_array_equal(s.simulate(np.random.default_rng(1), 500), e.simulate(np.random.default_rng(1), 500))

    alpha = 0.02
    out, ctx = _run(registry, "calibrated_threshold", {"false_alarm": alpha, "samples": 100_000},
                    {"scores": c2c["scores"]})
    [change] = out["change"]
    false_alarms = change.mask[~changed].mean()
    assert false_alarms == pytest.approx(alpha, rel=0.15), false_alarms
    assert change.mask[changed].all()  # 5 cm against a τ of about 1.4 cm (σ 4 mm and 3 mm, scores in cm)
    [cal] = ctx.notes["calibration"]
    assert cal["false_alarm_achieved"] == pytest.approx(alpha, rel=0.15) and cal["tau"] == change.threshold
    assert 1.0 < change.threshold < 2.0


def test_c2c_with_calibrated_threshold_in_a_workflow(cube_scene, registry) -> None:
    from pxr import Usd, UsdGeom

    from gdt_pipeline.runner import run_workflow

    wf = write_cube_workflow(cube_scene, distance="c2c")
    wf.write_text(wf.read_text().replace("  - uses: fixed\n    role: as-is\n    with: {tau: 10.0}\n",
                                         "  - uses: calibrated_threshold\n    role: as-is\n"
                                         "    with: {false_alarm: 0.01, samples: 20000}\n"))
    twin = run_workflow(wf, registry=registry).twin
    stage = Usd.Stage.Open(str(twin / "twin.usda"))
    state = np.asarray(UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Twin/E1_scan")).GetPrimvar("gdt:changeState").Get())
    flagged, truth = state == 1, cube_scene.changed
    # against a mesh only the normal part of the noise remains, so fewer unchanged points cross τ than simulated
    assert flagged[~truth].mean() <= 0.01
    assert flagged[truth].mean() > 0.95
