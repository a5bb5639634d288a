"""`gdt export --format las|laz`: LAS 1.4 files that laspy reads back with every per-point value of the twin, for
the composite at the epoch asked."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest

from gdt_pipeline.runner import run_workflow
from twin_store import STATE_COLORS, TwinStore

from .conftest import make_cube_scene, run_gdt, write_cube_workflow


@pytest.mark.parametrize("fmt", ["las", "laz"])
def test_las_export_carries_every_value_of_the_twin(tmp_path: Path, registry: object, fmt: str) -> None:
    scene = make_cube_scene(tmp_path / "cube")
    twin = run_workflow(write_cube_workflow(scene), registry=registry, twin=tmp_path / "twin").twin
    res = run_gdt("export", str(twin), "--format", fmt, "-o", str(tmp_path / "out"))
    assert res.returncode == 0, res.stderr
    sets = {es.key: es for es in TwinStore.open(twin).read_epoch("E1")}
    files = sorted((tmp_path / "out").glob(f"*.{fmt}"))
    assert [f.stem for f in files] == [k for k, es in sorted(sets.items()) if es.kind == "points"]
    for path in files:
        es, las = sets[path.stem], laspy.read(str(path))
        vis = np.asarray(es.visible, dtype=bool)
        assert las.header.version.minor == 4 and len(las.points) == int(vis.sum()) > 900
        xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
        assert np.max(np.abs(xyz - es.points[vis])) <= 0.5e-4 + 1e-9  # 0.1 mm integers in a metre twin
        assert np.array_equal(las.change_state, es.state[vis])
        assert np.array_equal(np.asarray(las.change_score), np.asarray(es.score, np.float32)[vis], equal_nan=True)
        assert np.array_equal(np.asarray(las.uncertainty), np.asarray(es.uncertainty_summary, np.float32)[vis])
        assert np.array_equal(las.source_epoch, es.source_epoch[vis])
        assert np.array_equal(las.fusion_reason, es.reason[vis])
        assert np.array_equal(np.asarray(las.fusion_ratio), np.asarray(es.reason_ratio, np.float32)[vis],
                              equal_nan=True)
        assert np.all(np.isnan(las.p_value)) == (es.p_value is None)
        colour = np.round(STATE_COLORS[es.state[vis]] * 65535).astype(np.uint16)
        assert np.array_equal(np.column_stack([las.red, las.green, las.blue]), colour)


def test_a_scans_las_classes_stay_in_the_twin_the_next_epoch_and_the_export(tmp_path: Path, registry) -> None:
    from gdt_pipeline.twin_reference import stored_composite

    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 10, (2000, 3))
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.scales, header.offsets = np.full(3, 1e-4), np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    classes = rng.choice(np.array([2, 5, 6], np.uint8), len(pts))
    las.classification = classes
    las.write(str(tmp_path / "scan.las"))
    (tmp_path / "wf.yaml").write_text(
        "name: classes\ntwin: twin\nepochs:\n  - id: E0\n    role: as-is\n    inputs:\n"
        "      - {path: scan.las, name: als, with: {attributes: [classification]}}\n"
        "stages:\n  - uses: constant\n    with: {model: isotropic, sigma: 0.01}\n  - uses: keep_unchanged\n")
    twin = run_workflow(tmp_path / "wf.yaml", registry=registry).twin
    store = TwinStore.open(twin)
    [es] = store.read_epoch("E0")
    assert np.array_equal(es.classification, classes)
    [item] = stored_composite(store, "E0", {"E0": "as-is"}).items  # what the next epoch is handed
    assert np.array_equal(item.dataset.fields["classification"], classes) and item.dataset.role == "as-is"
    assert run_gdt("export", str(twin), "--format", "las", "-o", str(tmp_path / "out")).returncode == 0
    assert np.array_equal(laspy.read(str(tmp_path / "out" / "E0_als.las")).classification, classes)
