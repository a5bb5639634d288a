"""Registration that knows when it failed, on simulated data: the schedule scaled to the data, the class filter,
the covariance checks (NaN or larger than the scene is an error) and the low-fitness warning (strict: an error)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from gdt_pipeline import Composite, CompositeItem, Dataset, EpochInfo, StageContext, StageError
from stages.registration._quality import Fit, check_covariance

from .test_registration import T_TRUE, cad_composite, scan_of, transform_errors

SHIFT = np.array([0.3, -0.2, 0.4])


def _points_composite(points: np.ndarray, fields: dict | None = None) -> Composite:
    n = len(points)
    return Composite((CompositeItem("E0_ref", Dataset("ref", "as-is", points, fields=fields or {}), "E0", np.zeros(n),
                                    np.full(n, np.nan), np.zeros(n), np.ones(n, bool)),))


def _run(registry, name: str, params: dict, recent: Dataset, comp: Composite):
    spec = registry.get(name)
    ctx = StageContext(stage=spec, params=spec.params.model_validate(params), slots={"recent": [recent],
                       "reference": comp}, epoch=EpochInfo("E1", 1, "as-is", 3, Path("."), "m"),
                       rng=np.random.default_rng(3), seed=3, log=logging.getLogger("gdt.stage.test"))
    return spec.run(ctx), ctx


def test_schedule_scales_with_the_data(registry) -> None:
    """The same scan at 1x and 100x: the derived voxels scale by 100 and the transform is recovered at both."""
    _, cad = cad_composite()
    ref, new = scan_of(cad, 0.002, seed=1)["points"], scan_of(cad, 0.002, seed=2)["points"]
    notes = []
    for scale in (1.0, 100.0):
        t = T_TRUE.copy()
        t[:3, 3] *= scale
        moved = (new * scale) @ t[:3, :3].T + t[:3, 3]
        out, ctx = _run(registry, "gicp", {}, Dataset("scan", "as-is", moved), _points_composite(ref * scale))
        angle, shift = transform_errors(out["registration"].transform, t, new * scale)
        assert angle < 0.05 and shift < 0.002 * scale, (scale, angle, shift)
        notes.append(ctx.notes["schedule"])
    assert notes[0]["derived"] and 0.004 < notes[0]["point_spacing"] < 0.007
    np.testing.assert_allclose(notes[1]["voxels"], np.asarray(notes[0]["voxels"]) * 100, rtol=0.02)
    np.testing.assert_allclose(notes[0]["voxels"], np.asarray([10, 4, 2]) * notes[0]["point_spacing"])


def _terrain(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rolling ground (class 2) with 'vegetation' (class 5) above it."""
    xy = rng.uniform(0, 100, (n, 2))
    z = 2 * np.sin(xy[:, 0] / 9) + 1.5 * np.cos(xy[:, 1] / 7) + rng.normal(0, 0.02, n)
    cls = np.where(rng.random(n) < 0.4, 5, 2).astype(np.uint8)
    z = z + np.where(cls == 5, rng.uniform(1, 10, n), 0.0)
    return np.column_stack([xy, z]), cls


def test_class_filter_fits_on_the_ground_and_moves_everything(registry) -> None:
    rng = np.random.default_rng(0)
    old, c_old = _terrain(rng, 20000)
    new, c_new = _terrain(rng, 20000)
    new[c_new == 5, 2] += 3.0  # the vegetation grew: a plain fit is pulled up
    moved = new + SHIFT
    comp = _points_composite(old, {"classification": c_old})
    recent = Dataset("scan", "as-is", moved, fields={"classification": c_new})
    out, ctx = _run(registry, "gicp", {"classes": [2]}, recent, comp)
    t = out["registration"].transform
    np.testing.assert_allclose(t[:3, 3], -SHIFT, atol=0.03)
    assert len(out["recent"][0].points) == 20000 and ctx.notes["warnings"] == []
    plain, ctx_plain = _run(registry, "gicp", {}, recent, comp)
    assert abs(plain["registration"].transform[2, 3] + SHIFT[2]) > 0.04  # the grown vegetation biased it
    assert "classes 5" in ctx_plain.notes["warnings"][0]


def test_class_filter_errors_name_the_dataset_and_class(registry) -> None:
    rng = np.random.default_rng(1)
    pts, cls = _terrain(rng, 2000)
    comp = _points_composite(pts, {"classification": cls})
    with pytest.raises(StageError, match=r"recent dataset 'scan' has no per-point classification"):
        _run(registry, "gicp", {"classes": [2]}, Dataset("scan", "as-is", pts), comp)
    with pytest.raises(StageError, match=r"`classes: \[6\]` selects 0 points of the recent data \('scan' 0"):
        _run(registry, "gicp", {"classes": [6]}, Dataset("scan", "as-is", pts, fields={"classification": cls}), comp)


def test_nan_or_huge_covariance_is_an_error() -> None:
    cov = np.eye(6) * 1e-6
    fit = Fit(0.9, 0.9, 0.01, 1000, cov, 1.0)
    check_covariance(fit, 10.0, "gicp", [])  # σ_t 1 mm in a 10 m scene: fine
    with pytest.raises(StageError, match=r"gicp: the transform's covariance is not finite.*fitness 0.01"):
        check_covariance(Fit(0.9, 0.9, 0.01, 3, np.full((6, 6), np.nan), 1.0), 10.0, "gicp", ["fitness 0.01"])
    huge = np.diag([1e-8] * 3 + [1e8, 1.0, 1.0])  # σ_tx 10 km
    with pytest.raises(StageError, match=r"σ is larger than the scene: σ_t \[10000.0, 1.0, 1.0\]"):
        check_covariance(Fit(0.9, 0.9, 0.01, 1000, huge, 1.0), 10.0, "gicp", [])


def test_flat_plane_leaves_the_shift_unconstrained(registry) -> None:
    """A flat, noiseless plane constrains z only: the point-to-plane normal equations say so, and that is an error."""
    g = np.stack(np.meshgrid(np.arange(60.0), np.arange(60.0)), -1).reshape(-1, 2)
    plane = np.column_stack([g, np.zeros(len(g))])
    with pytest.raises(StageError, match=r"covariance is not finite|σ is larger than the scene"):
        _run(registry, "point_to_plane", {}, Dataset("scan", "as-is", plane + np.array([0.2, 0.1, 0.3])),
             _points_composite(plane))


def test_low_fitness_warns_and_strict_refuses(registry, caplog) -> None:
    comp, cad = cad_composite()
    scan = scan_of(cad, 0.002)["points"]
    far = np.random.default_rng(2).uniform(-1, 1, (3 * len(scan), 3)) + np.array([0, 0, 20])  # 75 %: elsewhere
    recent = Dataset("scan", "as-is", np.vstack([scan, far]))
    with caplog.at_level(logging.WARNING, logger="gdt.stage.test"):
        _, ctx = _run(registry, "gicp", {}, recent, comp)
    fitness = ctx.notes["fitness"]
    assert fitness < 0.3 and ctx.notes["warnings"][0].startswith(f"fitness {fitness:.3g} ")
    assert "suspect registration: fitness" in caplog.text
    with pytest.raises(StageError, match=r"gicp \(strict\): the registration is suspect: fitness 0.0"):
        _run(registry, "gicp", {"strict": True}, recent, comp)
