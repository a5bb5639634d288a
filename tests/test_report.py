"""gdt report without a browser: the page is self-contained, says what it shows, lists the segments, obeys the point
budget with a deterministic voxel subsample, and reads large twins set by set (payload sets from their previews)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import gdt_pipeline.report.scene as report_scene
import twin_store.parts as parts
import twin_store.payloads as payloads
from gdt_pipeline.report import default_output, write_report
from gdt_pipeline.report.voxels import VoxelSampler, voxel_keys
from twin_store import STATE_NAMES, TwinStore

from .conftest import run_gdt
from .report_helpers import cube_twin, page_data, view_points
from .test_twin_store import mesh_set, points_set

OUTSIDE_SCRIPTS = re.compile(r"<script\b[^>]*>.*?</script>|<!--.*?-->", re.S)


@pytest.fixture(scope="module")
def twin(tmp_path_factory: pytest.TempPathFactory, registry) -> Path:
    return cube_twin(tmp_path_factory.mktemp("report"), registry)


@pytest.fixture(scope="module")
def page(twin: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[str, object]:
    out = tmp_path_factory.mktemp("page") / "report.html"
    summary = write_report(twin, out)
    return out.read_text(encoding="utf-8"), summary


def test_the_page_fetches_nothing(page: tuple[str, object]) -> None:
    html, _ = page
    markup = OUTSIDE_SCRIPTS.sub("", html)  # plotly.js (inlined) and its licence comment may name web addresses
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:)?//""", markup, re.I)
    assert not re.search(r"<script\b[^>]*\bsrc\s*=", html, re.I)
    assert not re.search(r"<link\b", html, re.I) and "@import" not in markup and "url(" not in markup
    assert re.search(r"<!--\nplotly\.js v\d+\.\d+\.\d+, embedded", html)
    assert "Permission is hereby granted" in html  # plotly's MIT licence text, in the comment


def test_the_page_says_what_it_shows(page: tuple[str, object], twin: Path) -> None:
    html, summary = page
    store = TwinStore.open(twin)
    counts = store.provenance("E1")["counts"]
    assert f"showing {summary.points_shown:,} of {summary.points_total:,} points (" in html
    assert summary.points_total == sum(len(p) for p in view_points(html).values())  # under the budget: all
    for name in STATE_NAMES:
        assert f"<td>{name.replace('_', ' ')}</td><td class=num>{counts.get(name, 0):,}</td>" in html
    segments = store.read_segments("E1")
    assert segments and any(s.kind == "new" for s in segments)
    rows = re.findall(r'<tr data-segment="(\d+)"', html)
    assert [int(r) for r in rows] == [s.id for s in segments]
    assert set(page_data(html)["segments"]) == {str(s.id) for s in segments}
    assert 'id="view3d"' in html and 'id="segments"' in html
    assert "τ = 10 (all datasets)" in html or "fixed: τ = 10" in html  # the fixed threshold, from its params
    assert "model <b>isotropic</b>" in html  # the uncertainty stage's model


def test_the_subsample_obeys_the_budget_and_is_deterministic(twin: Path, tmp_path: Path) -> None:
    first = write_report(twin, tmp_path / "a.html", budget=600)
    write_report(twin, tmp_path / "b.html", budget=600)
    assert 0 < first.points_shown <= 600 < first.points_total
    assert first.points_shown >= 0.8 * 600  # the voxel size is the smallest that fits: close to the budget
    assert (tmp_path / "a.html").read_bytes() == (tmp_path / "b.html").read_bytes()
    html = (tmp_path / "a.html").read_text(encoding="utf-8")
    assert f"showing {first.points_shown:,} of {first.points_total:,} points (voxel subsample" in html
    layers = view_points(html)
    assert sum(len(p) for p in layers.values()) == first.points_shown
    grid = page_data(html)["view"]["voxel"]
    assert f"one point per {grid['size']:.3g} m voxel" in html
    for xyz in layers.values():  # one point per occupied voxel and layer
        keys = voxel_keys(xyz, np.asarray(grid["origin"], np.float32), grid["size"])
        assert len(np.unique(keys)) == len(keys)


def test_the_voxel_sampler_is_spatial_bounded_and_order_stable() -> None:
    rng = np.random.default_rng(3)
    pts = rng.random((50_000, 3)).astype(np.float32)
    pts[:, 2] = 0  # a square: a surface like a scan's
    pts[:25_000, :2] *= 0.2  # dense in one corner: a systematic subsample would keep that density
    runs = []
    for chunk in (1000, 7777):
        sampler = VoxelSampler(2000, np.zeros(3, np.float32), np.ones(3, np.float32))
        for start in range(0, len(pts), chunk):
            sampler.add("layer", pts[start:start + chunk])
        kept, size = sampler.result()
        runs.append(kept["layer"])
        assert 1600 <= len(kept["layer"]) <= 2000 and size > 0
    corner = np.all(runs[0][:, :2] < 0.2, axis=1).mean()
    assert corner < 0.2  # spread over the area (the corner holds 4 % of it), not half of the points
    small = VoxelSampler(10**6, np.zeros(3, np.float32), np.ones(3, np.float32))
    small.add("layer", pts[:100])
    assert np.array_equal(small.result()[0]["layer"], pts[:100])  # within the budget: every point, in order


def test_the_command_writes_beside_the_twin_by_default(twin: Path) -> None:
    res = run_gdt("report", str(twin), "--epoch", "E0", "--budget", "1000")
    assert res.returncode == 0, res.stderr
    out = default_output(twin)
    assert out == twin.parent / f"{twin.name}_report.html" and out.is_file()
    assert f"wrote {out}" in res.stdout and "epoch E0" in res.stdout
    assert run_gdt("report", str(twin), "--epoch", "E9").returncode == 1


@pytest.fixture
def payload_twin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    # 200 points count as "large" here, in parts of 64, 64, 64 and 8 points, and the preview keeps every 4th;
    # the report's chunks (50 points) do not line up with the parts
    monkeypatch.setattr(payloads, "PAYLOAD_ELEMENTS", 100)
    monkeypatch.setattr(parts, "PART_ELEMENTS", 64)
    monkeypatch.setattr(payloads, "PREVIEW_POINTS", 50)
    monkeypatch.setattr(report_scene, "CHUNK", 50)
    store = TwinStore.create(tmp_path / "twin")
    store.write_epoch("E0", [mesh_set()], {"epoch": {"id": "E0", "index": 0, "role": "as-designed"}})
    store.write_epoch("E1", [mesh_set(), points_set()], {"epoch": {"id": "E1", "index": 1, "role": "as-is"}})
    return tmp_path / "twin"


def test_lean_reads_match_whole_reads_and_payload_sets_come_from_their_previews(payload_twin: Path,
                                                                               tmp_path: Path) -> None:
    store = TwinStore.open(payload_twin)
    whole = {es.key: es for es in store.read_epoch("E1")}
    for es in store.iter_sets("E1"):
        full = whole[es.key]
        for name, attr in (("state", "state"), ("visible", "visible"), ("score", "score"),
                           ("uncertainty", "uncertainty_summary"), ("source_epoch", "source_epoch")):
            assert np.array_equal(es.field(name), getattr(full, attr), equal_nan=True)
        local, origin = es.points()
        assert np.allclose(local + origin, full.points, atol=1e-4)
        pieces, same_origin = es.point_parts()
        pieces = list(pieces)
        assert np.array_equal(same_origin, origin) and np.array_equal(np.concatenate([p for _, p in pieces]), local)
        assert [first for first, _ in pieces] == ([0, 64, 128, 192] if es.kind == "points" else [0])
        assert es.has_preview == (es.kind == "points") and es.new_here == (es.key == "E1_scan")
    small = write_report(payload_twin, tmp_path / "small.html", budget=40)
    html = (tmp_path / "small.html").read_text(encoding="utf-8")
    assert small.points_total == 200 and small.points_shown <= 40
    assert "the payload sets E1_scan are drawn from their decimated previews" in html
    everything = write_report(payload_twin, tmp_path / "all.html", budget=1000)
    assert everything.points_shown == 200  # the budget asks for all: the set's own points are read
    assert "previews" not in (tmp_path / "all.html").read_text(encoding="utf-8").split('id="subsample"')[1][:400]


def test_a_plotly_js_without_typed_arrays_gets_plain_numbers() -> None:
    from gdt_pipeline.report.figures import typed
    from gdt_pipeline.report.page import TYPED_ARRAYS_SINCE, plain_arrays, plotly_asset

    assert plotly_asset().typed_arrays and plotly_asset().version >= TYPED_ARRAYS_SINCE
    figure = {"x": typed(np.array([1.5, 1 / 3], np.float32)), "i": typed(np.array([1, 2], np.int32)), "n": [3]}
    assert plain_arrays(figure) == {"x": [1.5, 0.3333333], "i": [1, 2], "n": [3]}
