"""Tiled runs against whole ones, on a generated scene no parameter was chosen on: the same states element by element,
scores within the float32 round-off of the ray casting, and the same twin from every executor (a real Dask
LocalCluster with two workers included)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pydantic import BaseModel, ConfigDict

from gdt_pipeline import GdtError, StageSpec, hookimpl
from gdt_pipeline.audit import audit_twin
from gdt_pipeline.runner import TilingOptions, run_workflow
from gdt_pipeline.simulation.suite import make_suite_scene
from twin_store import TwinStore

from .conftest import run_gdt

SCENE_SEED = 9101  # no other test or parameter choice looked at this scene
TILE_ELEMENTS = 25_000


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_suite_scene("precise", tmp_path_factory.mktemp("tiles") / "scene", SCENE_SEED).workflow


@pytest.fixture(scope="module")
def whole(scene: Path, registry: object) -> Path:
    return run_workflow(scene, registry=registry, twin=scene.parent / "whole").twin


def _elements(twin: Path) -> dict[tuple[str, str], object]:
    store = TwinStore.open(twin)
    return {(ep, es.key): es for ep in store.epochs() for es in store.read_epoch(ep)}


def _tiled(scene: Path, registry: object, name: str, **options: object) -> Path:
    tiling = TilingOptions(max_elements=TILE_ELEMENTS, **options)
    return run_workflow(scene, registry=registry, twin=scene.parent / name, tiling=tiling).twin


def _stage_report(twin: Path, epoch: str, stage: str) -> dict:
    return next(s["report"] for s in TwinStore.open(twin).provenance(epoch)["stages"] if s["uses"] == stage)


def test_tiled_run_equals_the_whole_run(scene: Path, whole: Path, registry: object,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from gdt_pipeline.runner import tiled as tiled_runner
    from gdt_pipeline.types import MappedRows

    spilled: list[str] = []
    spill = tiled_runner.spilled_points

    def counted(ds, folder):  # the scans the tiles read came from scratch files, and still gave the whole twin
        out = spill(ds, folder)
        if isinstance(out.points, MappedRows):
            spilled.append(ds.name)
        return out

    monkeypatch.setattr(tiled_runner, "spilled_points", counted)
    tiled = _tiled(scene, registry, "tiled")
    assert spilled, "no scan was moved to a scratch file"
    a, b = _elements(whole), _elements(tiled)
    assert a.keys() == b.keys()
    scored = 0
    for key, x in a.items():
        y = b[key]
        assert np.array_equal(x.state, y.state), key
        assert np.array_equal(x.visible, y.visible), key
        assert np.array_equal(x.source_epoch, y.source_epoch), key
        if x.covariance is not None:
            assert np.allclose(x.covariance, y.covariance, rtol=1e-6, atol=0), key  # float32 in the twin
        both = np.isfinite(x.score)
        assert np.array_equal(both, np.isfinite(y.score)), key
        # Open3D casts rays in float32 about the centre of what it holds: a tile's centre is not the scene's
        assert np.allclose(x.score[both], y.score[both], rtol=2e-3, atol=1e-6), key
        scored += int(both.sum())
    assert scored > 50_000
    report = _stage_report(tiled, "E1", "auto")["tiling"]
    assert report["tiles"] > 3
    # sensor_model's normals reach past a halo of 0: those tiles ran again, wider
    assert _stage_report(tiled, "E1", "sensor_model")["tiling"]["tiles_with_wider_halo"] > 0
    tau = [_stage_report(t, "E1", "calibrated_threshold")["calibration"] for t in (whole, tiled)]
    assert tau[0] == tau[1]
    audit = audit_twin(tiled, registry=registry)  # re-run in the tiles the run recorded
    assert audit.ok and all(e.exact for e in audit.epochs)


class _Boom(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _boom(ctx: object) -> dict:
    raise ValueError("dataset 'scan': no threshold today")


class _BoomPlugin:
    @staticmethod
    @hookimpl
    def gdt_stages() -> list[StageSpec]:
        return [StageSpec(name="boom", family="threshold", version="0", params=_Boom, run=_boom, tiling="tile",
                          requires=("scores",), provides=("change",))]


def test_a_stage_failing_in_a_tile_names_the_stage_and_the_tile(tmp_path: Path) -> None:
    from gdt_pipeline.plugins import load_registry

    from .conftest import make_cube_scene, write_cube_workflow

    scene = make_cube_scene(tmp_path / "cube")
    wf = write_cube_workflow(scene)
    fixed = "uses: fixed\n    role: as-is\n    with: {tau: 10.0}"
    wf.write_text(wf.read_text().replace(fixed, "uses: boom\n    role: as-is"))
    registry = load_registry(extra=[("boom", _BoomPlugin)])
    where = r"epoch E1, stage 5 'boom', tile \d+ failed: ValueError: dataset 'scan': no threshold today"
    with pytest.raises(GdtError, match=where):
        run_workflow(wf, registry=registry, twin=tmp_path / "t", tiling=TilingOptions(tile=0.5))
    assert not (tmp_path / "t").exists()


def test_dask_and_process_pools_give_the_serial_twin(scene: Path, registry: object) -> None:
    serial = _elements(_tiled(scene, registry, "serial"))
    for executor in ("dask", "processes"):
        other = _elements(_tiled(scene, registry, executor, executor=executor, workers=2))
        assert serial.keys() == other.keys()
        for key, x in serial.items():
            y = other[key]
            for field in ("state", "visible", "covariance", "uncertainty_summary"):
                assert np.array_equal(getattr(x, field), getattr(y, field)), (executor, key, field)
            assert np.array_equal(x.score, y.score, equal_nan=True), (executor, key)


def test_cli_asks_for_tiles_and_names_the_executors(scene: Path, tmp_path: Path) -> None:
    res = run_gdt("run", str(scene), "--twin", str(tmp_path / "t"), "--executor", "dask")
    assert res.returncode != 0 and "give --tile or --tile-elements" in res.stderr
    res = run_gdt("run", str(scene), "--twin", str(tmp_path / "t"), "--executor", "slurm", "--tile", "1")
    assert res.returncode != 0
    assert "unknown executor 'slurm'" in res.stderr and "dask, processes, serial" in res.stderr


def test_validate_names_an_unknown_executor_where_it_is(scene: Path) -> None:
    wf = scene.parent / "dusk.yaml"
    wf.write_text(scene.read_text() + "execution:\n  executor: dusk\n  tile: 1.0\n")
    res = run_gdt("validate", str(wf))
    assert res.returncode != 0
    assert "execution.executor: unknown executor 'dusk'" in res.stdout and "dask" in res.stdout


class _WholeNearestPlugin:
    """``nearest`` as a whole-epoch stage: the tiled distance and threshold after it get its correspondences cut."""

    @staticmethod
    @hookimpl
    def gdt_stages() -> list[StageSpec]:
        import dataclasses

        from gdt_pipeline.plugins import load_registry

        nearest = load_registry(blocked={"gdt-c2c", "gdt-m3c2"}).get("nearest")
        return [dataclasses.replace(nearest, name="nearest_whole", tiling="epoch", reach=None)]


def test_correspondences_made_whole_are_cut_into_tiles(tmp_path: Path) -> None:
    from gdt_pipeline.plugins import load_registry

    from .conftest import make_cube_scene, write_cube_workflow

    scene = make_cube_scene(tmp_path / "cube")
    wf = write_cube_workflow(scene)
    wf.write_text(wf.read_text().replace("uses: nearest\n", "uses: nearest_whole\n"))
    registry = load_registry(extra=[("whole_nearest", _WholeNearestPlugin)])
    whole = _elements(run_workflow(wf, registry=registry, twin=tmp_path / "whole").twin)
    tiled_twin = run_workflow(wf, registry=registry, twin=tmp_path / "tiled", tiling=TilingOptions(tile=0.3)).twin
    tiled = _elements(tiled_twin)
    assert _stage_report(tiled_twin, "E1", "bhattacharyya")["tiling"]["tiles"] > 8
    for key, x in whole.items():
        assert np.array_equal(x.state, tiled[key].state), key
        assert np.array_equal(x.score, tiled[key].score, equal_nan=True), key
    assert int(np.sum(whole[("E1", "E1_scan")].state == 1)) > 500  # the new box is found


def test_welch_m3c2_with_cloud_normals_is_the_same_whole_or_in_tiles(cube_scene, registry: object) -> None:
    """A third epoch scans the cube scene again: against the new box's points kept from E1, welch_m3c2 takes the
    recent cloud's k-nearest PCA normals (20 points, about 5 cm on the box), which a tile whose halo is the 1 cm
    search radius must widen to see whole (declared neighbourhoods), about the epoch's origin."""
    from .conftest import make_cube_scene, write_cube_workflow

    rescan = make_cube_scene(cube_scene.dir.parent / "rescan", seed=1)  # the same scene, other noise
    (cube_scene.dir / "scan2.ply").write_bytes(rescan.scan.read_bytes())
    wf = write_cube_workflow(cube_scene, distance="welch_m3c2")
    again = "  - id: E2\n    role: as-is\n    inputs: [{path: scan2.ply, name: again}]\n"
    text = wf.read_text().replace("stages:\n", again + "stages:\n")
    text = text.replace("  - uses: nearest\n    role: as-is\n", "  - uses: nearest\n    role: as-is\n"
                                                                  "    with: {max_distance: 0.01}\n")
    wf.write_text(text.replace("uses: fixed\n    role: as-is\n    with: {tau: 10.0}",
                               "uses: significance\n    role: as-is\n    with: {alpha: 0.01}"))
    whole = run_workflow(wf, registry=registry, twin=cube_scene.dir / "welch_whole").twin
    tiled = run_workflow(wf, registry=registry, twin=cube_scene.dir / "welch_tiled",
                         tiling=TilingOptions(tile=0.15)).twin
    prov = TwinStore.open(tiled).provenance("E2")
    [welch] = [s for s in prov["stages"] if s["uses"] == "welch_m3c2"]
    assert welch["report"]["tiling"]["tiles"] > 1 and welch["report"]["tiling"]["tiles_with_wider_halo"] > 0
    a, b = _elements(whole), _elements(tiled)
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key].state, b[key].state, err_msg=str(key))
        both = np.isfinite(a[key].score)
        np.testing.assert_array_equal(both, np.isfinite(b[key].score), err_msg=str(key))
        # against the CAD, Open3D's closest points are float32 about the centre of what a tile holds (see above):
        # |t| agrees to 1e-4, where thresholds lie near 2.6
        np.testing.assert_allclose(a[key].score[both], b[key].score[both], rtol=2e-3, atol=1e-4, err_msg=str(key))
    # the new box's points of E2 are paired with E1's kept points of it: cloud normals, bit for bit
    box = cube_scene.changed
    x, y = a[("E2", "E2_again")].score[box], b[("E2", "E2_again")].score[box]
    assert np.isfinite(x).sum() > 0.3 * box.sum() and np.nanmax(x) > 1.0  # scored, along normals that matter
    np.testing.assert_array_equal(x, y)
