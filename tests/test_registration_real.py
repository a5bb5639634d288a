"""Registration on real airborne LiDAR (issue 34): Tommy Thompson Park, Toronto, 2015 (twin) and 2023 (recent). The
2023 ground sits 0.41 m below 2015, a datum offset. The default registrar with only ``classes: [2]`` must remove it;
without the class filter it must warn; the 5/2/1 cm voxels of earlier releases must fail loudly, not silently.

The residual is measured on the 2023 ground: z minus the z of the nearest 2015 ground point in xy (within 3 m).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gdt_pipeline import Composite, CompositeItem, Dataset, EpochInfo, StageContext, StageError

from .conftest import REPO, SHARED_DATA

DATA = SHARED_DATA / "ttp_toronto_als"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data/ttp_toronto_als absent")


@pytest.fixture(scope="module")
def pair() -> tuple[Dataset, Dataset]:
    """Both epochs as the LAS reader gives them with its default parameters (classification kept)."""
    from stages.io.las import LasParams, read_las

    attrs = tuple(LasParams().attributes)
    out = []
    for year in ("2015", "2023"):
        pts, fields = read_las(DATA / f"TTP_{year}.laz", None, attrs)
        out.append(Dataset(f"als_{year}", "as-is", pts, fields=fields))
    return out[0], out[1]


def _register(registry, name: str, params: dict, pair: tuple[Dataset, Dataset]):
    old, new = pair
    n = old.n_elements
    comp = Composite((CompositeItem("E2015_als_2015", old, "E2015", np.zeros(n), np.full(n, np.nan), np.zeros(n),
                                    np.ones(n, bool)),))
    spec = registry.get(name)
    ctx = StageContext(stage=spec, params=spec.params.model_validate(params),
                       slots={"recent": [new], "reference": comp},
                       epoch=EpochInfo("E2023", 1, "as-is", 34, Path("."), "m"), rng=np.random.default_rng(34),
                       seed=34, log=logging.getLogger("gdt.stage.test"))
    return spec.run(ctx), ctx


def ground_residual(pair: tuple[Dataset, Dataset], moved: np.ndarray) -> tuple[float, float]:
    """Median and IQR of the 2023 ground's z minus its nearest 2015 ground point's (in xy, within 3 m)."""
    old, new = pair
    g15 = old.points[old.fields["classification"] == 2]
    g23 = moved[new.fields["classification"] == 2]
    d, j = cKDTree(g15[:, :2]).query(g23[:, :2], distance_upper_bound=3.0)
    ok = np.isfinite(d)
    dz = g23[ok, 2] - g15[j[ok], 2]
    q1, q3 = np.percentile(dz, [25, 75])
    return float(np.median(dz)), float(q3 - q1)


def test_the_offset_is_there(pair) -> None:
    median, iqr = ground_residual(pair, pair[1].points)
    assert median == pytest.approx(-0.41, abs=0.01) and iqr < 0.13


@pytest.mark.parametrize("name", ["stable_areas", "gicp"])
def test_default_registrar_on_the_ground_class_removes_the_datum_offset(registry, pair, name: str) -> None:
    out, ctx = _register(registry, name, {"classes": [2]}, pair)
    median, iqr = ground_residual(pair, out["recent"][0].points)
    assert abs(median) <= 0.03 and iqr <= 0.13, (median, iqr)
    sigma_t = np.sqrt(np.diag(out["registration"].covariance)[3:])
    assert np.isfinite(sigma_t).all() and sigma_t.max() <= 0.1, sigma_t
    assert ctx.notes["shift_at_center"][2] == pytest.approx(0.41, abs=0.03)
    assert ctx.notes["schedule"]["derived"] and ctx.notes["warnings"] == []
    assert ctx.notes["fitness"] > 0.8 and len(out["recent"][0].points) == pair[1].n_elements  # every point moved


def test_stable_areas_defaults_on_every_class_warn(registry, pair, caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="gdt.stage.test"):
        _, ctx = _register(registry, "stable_areas", {"trim_rounds": 1}, pair)
    assert len(ctx.notes["warnings"]) == 1 and "49% of the recent points" in ctx.notes["warnings"][0]
    assert "classes: [2]" in caplog.text
    with pytest.raises(StageError, match=r"strict.*49% of the recent points"):
        _register(registry, "stable_areas", {"trim_rounds": 0, "strict": True}, pair)


def test_object_scale_voxels_fail_loudly(registry, pair) -> None:
    """The 5/2/1 cm voxels of earlier releases: point_to_plane reported σ_t of 13 km and was accepted."""
    with pytest.raises(StageError, match=r"σ.*fitness [0-9.e-]+ \(share of the recent points"):
        _register(registry, "point_to_plane", {"voxels": [0.05, 0.02, 0.01]}, pair)


def test_the_workflow_validates(registry) -> None:
    from gdt_pipeline.workflow import load_workflow

    wf = load_workflow(REPO / "workflows" / "real" / "toronto_als.yaml", registry)
    reg = next(st for st in wf.model.stages if st.uses == "stable_areas")
    assert reg.with_.classes == [2] and reg.with_.voxels is None  # the defaults, scaled to the data
