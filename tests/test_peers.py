"""The M3C2 peers on a generated scene: a noisy plane in which a square was lifted by 3 cm."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("py4dgeo")

from gdt_pipeline.evaluation import peers


@pytest.fixture(scope="module")
def lifted_plane() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)

    def plane(n: int) -> np.ndarray:
        return np.column_stack([rng.uniform(0, 1, n), rng.uniform(0, 1, n), rng.normal(0, 0.001, n)])

    ref, query = plane(30000), plane(20000)
    lifted = (np.abs(query[:, 0] - 0.5) < 0.1) & (np.abs(query[:, 1] - 0.5) < 0.1)
    query[lifted, 2] += 0.03
    return ref, query, lifted


def _far(query: np.ndarray) -> np.ndarray:
    """Unchanged points whose cylinder cannot reach the lifted square's rim (M3C2 averages over the cylinder)."""
    return (np.abs(query[:, 0] - 0.5) > 0.14) | (np.abs(query[:, 1] - 0.5) > 0.14)


def test_m3c2_flags_the_lifted_square_and_its_lod_is_linear_in_the_registration_error(lifted_plane) -> None:
    ref, query, lifted = lifted_plane
    kw = {"cyl_radius": 0.02, "normal_radii": (0.08,), "max_distance": 0.2}
    res = peers.m3c2(ref, query, **kw)
    assert len(res.distance) == len(query)
    assert res.changed[lifted].mean() > 0.95
    # a 95 % level of detection on unchanged, well-sampled surfaces: about 5 % false alarms, not more than ~8 %
    assert res.changed[_far(query)].mean() < 0.08
    inner = lifted & (np.abs(query[:, 0] - 0.5) < 0.07) & (np.abs(query[:, 1] - 0.5) < 0.07)
    assert np.nanmedian(res.distance[inner]) == pytest.approx(0.03, abs=0.002)  # query minus reference: positive
    with_reg = peers.m3c2(ref, query, registration_error=0.004, **kw)
    np.testing.assert_allclose(with_reg.lod, peers.m3c2_lod_with_registration_error(res, 0.004), atol=1e-12)
    assert np.all(with_reg.lod[np.isfinite(res.lod)] > res.lod[np.isfinite(res.lod)])
    assert with_reg.changed[_far(query)].mean() < 0.001  # 4 mm registration error: the 1 mm noise never exceeds LoD


def test_m3c2_ep_on_a_subsample_detects_the_lift_with_the_sign_of_m3c2(lifted_plane) -> None:
    ref, query, lifted = lifted_plane
    origin = np.array([[0.5, 0.5, 2.0]])
    res = peers.m3c2_ep(ref, query, reference_origins=origin, query_origins=origin,
                        reference_scanpos=np.ones(len(ref), np.int32), query_scanpos=np.ones(len(query), np.int32),
                        cyl_radius=0.02, normal_radii=(0.08,), max_distance=0.2, sigma_range=0.001,
                        sigma_scan=2e-4, sigma_yaw=2e-4, max_core_points=300, seed=1)
    assert len(res.core_index) == 300 == len(res.distance)
    on = lifted[res.core_index]
    assert on.sum() >= 5
    assert res.changed[on].mean() > 0.9
    assert res.changed[_far(query)[res.core_index]].mean() < 0.1
    assert np.nanmedian(res.distance[on]) == pytest.approx(0.03, abs=0.003)
