"""Where the reference has data (``gdt_pipeline.coverage``): an element without a correspondence is new only where
the reference covers its place, not comparable elsewhere; known elements nothing recent tested are not unchanged;
and the ``coverage`` region of view finds removal without stations."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import trimesh

from gdt_pipeline import ChangeState, Composite, CompositeItem, Dataset
from gdt_pipeline.coverage import reference_coverage, rim_edges
from gdt_pipeline.runner import run_workflow
from twin_store import TwinStore

from .conftest import write_points_ply


def _item(ds: Dataset) -> CompositeItem:
    n = ds.n_elements
    return CompositeItem(key=ds.name, dataset=ds, epoch="E0", state=np.zeros(n, np.uint8), score=np.full(n, np.nan),
                         source_epoch=np.zeros(n, np.int32), visible=np.ones(n, bool))


def test_rim_edges_are_the_edges_one_facet_uses() -> None:
    plate = trimesh.creation.box(extents=(1, 1, 1))
    assert not rim_edges(plate.faces).any()  # closed: no rim
    square = np.array([[0, 1, 2], [0, 2, 3]])
    rims = rim_edges(square)
    # the diagonal 0-2 is shared (opposite corner 1 of the first facet, corner 3 of the second): 4 rim edges
    assert rims.sum() == 4 and not rims[0, 1] and not rims[1, 2]


def test_an_open_mesh_covers_what_lies_over_it_and_a_closed_one_everything() -> None:
    square = Dataset("plate", "as-is", np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float),
                     np.array([[0, 1, 2], [0, 2, 3]]))
    query = np.array([[0.5, 0.5, 0.3], [0.2, 0.9, -0.01], [1.5, 0.5, 0.0], [0.5, -0.4, 0.2], [3.0, 3.0, 3.0]])
    found = reference_coverage(Composite((_item(square),)), query, np.full(5, 0.01))
    assert found.covered.tolist() == [True, True, False, False, False]
    np.testing.assert_allclose(found.looked[:2], [0.3, 0.01], atol=1e-6)
    box = trimesh.creation.box(extents=(1, 1, 1))
    closed = Dataset("box", "as-designed", np.asarray(box.vertices), np.asarray(box.faces))
    assert reference_coverage(Composite((_item(closed),)), query, np.full(5, 0.01)).covered.all()


def test_a_cloud_covers_its_own_sampling_at_the_element_scale() -> None:
    g = np.arange(0.0, 1.0001, 0.02)
    grid = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    cloud = Dataset("scan", "as-is", np.c_[grid, np.zeros(len(grid))])
    query = np.array([[0.5, 0.5, 0.05], [1.05, 0.5, 0.0], [1.2, 0.5, 0.0], [0.5, 0.5, 0.5]])
    found = reference_coverage(Composite((_item(cloud),)), query, np.array([0.0, 0.0, 0.0, 0.2]))
    # spacing 0.02 (the 4th neighbour at 0.02): within 3 spacings plus the element's own 99 % radius
    assert found.covered.tolist() == [True, True, False, False]


WORKFLOW = """\
name: strip
twin: twin
seed: 3
epochs:
  - id: E0
    role: as-is
    inputs: [{{path: old.ply}}]
  - id: E1
    role: as-is
    inputs: [{{path: new.ply}}]
stages:
  - uses: constant
    with: {{model: isotropic, sigma: 0.002}}
{rov}  - uses: auto
    role: as-is
    epochs: [E1]
  - uses: bhattacharyya
    epochs: [E1]
  - uses: calibrated_threshold
    epochs: [E1]
  - uses: keep_unchanged
"""


def _plane(x0: float, x1: float, step: float, z: float = 0.0) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(x0, x1 + 1e-9, step), np.arange(0.0, 1.0 + 1e-9, step))
    return np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, z)]


def _run(tmp_path: Path, old: np.ndarray, new: np.ndarray, rov: str = "") -> tuple[list, dict]:
    write_points_ply(tmp_path / "old.ply", old)
    write_points_ply(tmp_path / "new.ply", new)
    wf = tmp_path / "wf.yaml"
    wf.write_text(textwrap.dedent(WORKFLOW.format(rov=rov)))
    twin = run_workflow(wf).twin
    sets = {es.key: es for es in TwinStore.open(twin).read_epoch("E1")}
    return [sets["E0_old"], sets["E1_new"]], TwinStore.open(twin).provenance("E1")


def test_a_strip_the_reference_never_reached_is_not_comparable_and_untested_known_data_not_unchanged(
        tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    old = _plane(0.0, 1.0, 0.02) + rng.normal(0, 0.002, (2601, 3))
    new_plane = _plane(0.5, 2.0, 0.02)
    new = new_plane + rng.normal(0, 0.002, new_plane.shape)
    box = _plane(0.6, 0.8, 0.02, z=0.3)[:100]  # a new object in front of the plane the reference sampled
    (known, recent), prov = _run(tmp_path, old, np.vstack([new, box]))
    x = recent.points[:, 0]
    on_plane = np.arange(len(recent.state)) < len(new)
    beyond = on_plane & (x > 1.15)  # beyond 3 spacings plus the 99 % radius of the old edge
    assert beyond.sum() > 2000 and np.all(recent.state[beyond] == ChangeState.NOT_COMPARABLE)
    assert np.all(recent.visible[beyond])  # it still comes in: the twin had no data there
    inside = on_plane & (x < 0.95)
    assert np.mean(recent.state[inside] == ChangeState.UNCHANGED) > 0.97
    # the new object 0.3 m in front is not within the reference's sampling either: without stations, not comparable
    assert np.all(recent.state[~on_plane] != ChangeState.UNCHANGED)
    # known points the recent scan never reached (x < 0.45) were not tested: not comparable, never unchanged
    untested = known.points[:, 0] < 0.45
    assert np.all(known.state[untested] == ChangeState.NOT_COMPARABLE)
    assert np.mean(known.state[known.points[:, 0] > 0.55] == ChangeState.UNCHANGED) > 0.97
    cal = next(s for s in prov["stages"] if s["uses"] == "calibrated_threshold")["report"]["calibration"][0]
    assert cal["decided"]["not_comparable"] == int(np.sum(recent.state == ChangeState.NOT_COMPARABLE))
    assert cal["false_alarm_achieved"] >= cal["false_alarm_simulated"] - 1e-12


def test_coverage_region_of_view_finds_removal_along_a_stated_sight(tmp_path: Path) -> None:
    """Airborne-like data: a roof 1 m above the ground is gone in E1, where only ground returns remain (every
    return in its column lies beyond it along the nadir sight): removed. Where a canopy (z 1.5) now stands above
    the old roof, nothing says whether the roof is still there: not seen. The ground is matched."""
    rng = np.random.default_rng(5)
    ground = _plane(0.0, 2.0, 0.05)
    roof = _plane(0.5, 1.5, 0.05, z=1.0)
    canopy = _plane(1.2, 1.6, 0.05, z=1.5)
    old = np.vstack([ground, roof]) + rng.normal(0, 0.002, (len(ground) + len(roof), 3))
    new = np.vstack([ground, canopy]) + rng.normal(0, 0.002, (len(ground) + len(canopy), 3))
    rov = "  - uses: coverage\n    epochs: [E1]\n    with: {sight: [0, 0, -1]}\n"
    (known, _), prov = _run(tmp_path, old, new, rov)
    is_roof = np.arange(len(known.state)) >= len(ground)
    x = known.points[:, 0]
    open_roof = is_roof & (x < 0.9)
    under_canopy = is_roof & (x > 1.35)
    assert np.all(known.state[open_roof] == ChangeState.REMOVED) and not known.visible[open_roof].any()
    assert np.all(known.state[under_canopy] == ChangeState.OUTSIDE_ROV) and known.visible[under_canopy].all()
    assert np.mean(known.state[~is_roof] == ChangeState.UNCHANGED) > 0.99
    report = next(s for s in prov["stages"] if s["uses"] == "coverage")["report"]
    assert report["removed"] == int(np.sum(known.state == ChangeState.REMOVED))


def test_coverage_without_a_sight_removes_what_the_recent_cloud_samples_around(tmp_path: Path) -> None:
    """No sight: a known strip whose surroundings the recent cloud samples densely but that has no recent point is
    removed; known data far from every recent point is not seen."""
    rng = np.random.default_rng(6)
    old = _plane(0.0, 2.0, 0.02) + rng.normal(0, 0.001, (5151, 3))
    new_pts = _plane(0.0, 1.0, 0.02)
    new_pts = new_pts[np.abs(new_pts[:, 0] - 0.5) > 0.03]  # a 4 cm gap at x = 0.5 (two spacings each side)
    (known, _), _ = _run(tmp_path, old, new_pts + rng.normal(0, 0.001, new_pts.shape),
                         "  - uses: coverage\n    epochs: [E1]\n")
    x = known.points[:, 0]
    assert np.all(known.state[np.abs(x - 0.5) < 0.005] == ChangeState.REMOVED)
    assert np.all(known.state[x > 1.3] == ChangeState.OUTSIDE_ROV)
    assert np.mean(known.state[(x < 0.4) | ((x > 0.6) & (x < 0.95))] == ChangeState.UNCHANGED) > 0.97


def test_not_comparable_is_the_same_whole_or_in_tiles(tmp_path: Path) -> None:
    """Coverage is judged over the whole epoch after a tiled distance stage, and a tiled threshold's finish turns
    the elements without a score into not comparable there: the states match the whole run's."""
    from gdt_pipeline.runner import TilingOptions

    rng = np.random.default_rng(7)
    write_points_ply(tmp_path / "old.ply", _plane(0.0, 1.0, 0.02) + rng.normal(0, 0.002, (2601, 3)))
    new = _plane(0.5, 2.0, 0.02)
    write_points_ply(tmp_path / "new.ply", new + rng.normal(0, 0.002, new.shape))
    wf = tmp_path / "wf.yaml"
    wf.write_text(textwrap.dedent(WORKFLOW.format(rov="")).replace(
        "  - uses: calibrated_threshold\n    epochs: [E1]\n",
        "  - uses: fixed\n    epochs: [E1]\n    with: {tau: 3.0}\n"))
    states = []
    for name, tiling in (("whole", None), ("tiled", TilingOptions(tile=0.4))):
        twin = run_workflow(wf, twin=tmp_path / name, tiling=tiling).twin
        states.append({es.key: es.state for es in TwinStore.open(twin).read_epoch("E1")})
    assert np.sum(states[0]["E1_new"] == ChangeState.NOT_COMPARABLE) > 2000
    for key, whole in states[0].items():
        assert np.array_equal(whole, states[1][key]), key
