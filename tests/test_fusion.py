"""Fusion policies (which data the composite keeps) and the segments of what an epoch changed."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from gdt_pipeline import (
    BoxUncertainty,
    Change,
    Composite,
    CompositeItem,
    Dataset,
    EpochInfo,
    GaussianUncertainty,
    ItemView,
    RegionOfView,
)
from gdt_pipeline.plugins import StageContext, load_registry


@pytest.fixture(scope="module")
def registry():
    return load_registry()


def _plane(x0: float, n: int, rng: np.random.Generator, sigma: float) -> np.ndarray:
    p = np.column_stack([rng.uniform(x0, x0 + 1, n), rng.uniform(0, 1, n), np.zeros(n)])
    p[:, 2] += rng.normal(0, sigma, n)
    return p


def _gauss(points: np.ndarray, sigma: float, name: str, role: str = "as-is") -> Dataset:
    cov = np.broadcast_to(np.eye(3) * sigma**2, (len(points), 3, 3))
    return Dataset(name, role, points).with_uncertainty(GaussianUncertainty(cov))


def _item(ds: Dataset, epoch: str) -> CompositeItem:
    n = ds.n_elements
    return CompositeItem(f"{epoch}_{ds.name}", ds, epoch, np.zeros(n, np.uint8), np.zeros(n), np.zeros(n, np.int32),
                         np.ones(n, bool))


def _run(registry, name: str, reference: Composite, recent: list[Dataset], changes: list[Change], **params):
    spec = registry.get(name)
    info = EpochInfo(id="E2", index=2, role="as-is", seed=0, workflow_dir=".", units="m")
    rov = RegionOfView.box([-1, -1, -1], [3, 2, 1])
    everything = {it.key: ItemView(np.ones(it.dataset.n_elements, bool), np.ones(it.dataset.n_elements, bool))
                  for it in reference.items}
    rov = RegionOfView(rov.vertices, rov.faces, views=everything)
    slots = {"recent": recent, "reference": reference, "change": changes, "rov": rov, "epoch": info}
    ctx = StageContext(stage=spec, params=spec.params(**params), slots=slots, epoch=info,
                       rng=np.random.default_rng(0), seed=0, log=logging.getLogger("test"))
    return spec.run(ctx)["composite"], ctx.notes


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(0)
    # known: a CAD plate (as-designed, ±1 mm box) on x in [0, 1] and a noisy earlier scan (1 cm) on x in [1, 2]
    # (a 2 cm grid of facets: the fusion matches data to facet centroids, so a CAD's facets must not dwarf it)
    g = np.linspace(0, 1, 51)
    yy, xx = np.meshgrid(g, g, indexing="ij")
    cad_pts = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    idx = np.arange(cad_pts.shape[0]).reshape(51, 51)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    cad = Dataset("cad", "as-designed", cad_pts, faces=np.vstack([np.column_stack([a, b, c]),
                                                                    np.column_stack([a, c, d])]))
    cad = cad.with_uncertainty(BoxUncertainty(half_widths=np.array([[0.001, 0.001, 0.001]])))
    tof = _gauss(_plane(1.0, 3000, rng, 0.01), 0.01, "tof")
    reference = Composite((_item(cad, "E0"), _item(tof, "E1")))
    # recent: a precise scan (0.1 mm) of both, unchanged
    precise = _gauss(np.vstack([_plane(0.0, 3000, rng, 1e-4), _plane(1.0, 3000, rng, 1e-4)]), 1e-4, "sl")
    n = precise.n_elements
    change = Change(query=0, score=np.zeros(n), mask=np.zeros(n, bool), state=np.zeros(n, np.uint8))
    return reference, precise, change


def test_most_reliable_replaces_the_noisy_scan_and_keeps_the_design(registry, scene) -> None:
    reference, precise, change = scene
    comp, notes = _run(registry, "most_reliable", reference, [precise], [change])
    items = {it.key: it for it in comp.items}
    assert items["E0_cad"].visible.all()  # the design stays where the precise scan confirms it
    # the 1 cm scan is replaced where the 0.1 mm scan images it; its points beyond ~3σ of the precise surface
    # (about 1 %) are not imaged by it and stay
    assert items["E1_tof"].visible.sum() <= 30
    on_tof = precise.points[:, 0] > 1.0
    sl = items["E2_sl"]
    # the precise points on the old scan come in; on the CAD (away from the seam at x = 1) they stay hidden
    assert sl.visible[on_tof].mean() > 0.99 and not sl.visible[precise.points[:, 0] < 0.95].any()
    assert notes["fusion"]["replaced"]["E1_tof"] >= 2970
    # replace_in_view takes the newest everywhere; keep_unchanged nowhere
    comp, _ = _run(registry, "replace_in_view", reference, [precise], [change])
    items = {it.key: it for it in comp.items}
    assert items["E0_cad"].visible.mean() < 0.05 and items["E2_sl"].visible.mean() > 0.99
    comp, _ = _run(registry, "keep_unchanged", reference, [precise], [change])
    items = {it.key: it for it in comp.items}
    assert items["E0_cad"].visible.all() and items["E1_tof"].visible.all() and not items["E2_sl"].visible.any()
    with pytest.raises(ValueError, match="region-of-view"):
        spec = registry.get("most_reliable")
        info = EpochInfo(id="E2", index=2, role="as-is", seed=0, workflow_dir=".", units="m")
        ctx = StageContext(stage=spec, params=spec.params(), epoch=info, rng=np.random.default_rng(0), seed=0,
                           slots={"recent": [precise], "reference": reference, "change": [change], "epoch": info},
                           log=logging.getLogger("test"))
        spec.run(ctx)


def test_new_elements_come_out_as_segments_with_artefacts_flagged(registry, scene) -> None:
    reference, _, _ = scene
    rng = np.random.default_rng(1)
    blobs = [rng.normal(c, 0.01, (200, 3)) for c in ([0.3, 0.3, 0.2], [1.6, 0.7, 0.3])]
    stray = np.array([[0.9, 0.9, 0.5], [1.9, 0.1, 0.6]])
    pts = np.vstack([*blobs, stray])
    new = _gauss(pts, 1e-3, "sl")
    n = len(pts)
    change = Change(query=0, score=np.full(n, 50.0), mask=np.ones(n, bool), state=np.full(n, 1, np.uint8))
    comp, notes = _run(registry, "keep_unchanged", reference, [new], [change], min_segment_size=5,
                        segment_radius=0.05)
    real = [g for g in comp.segments if not g.artefact]
    assert len(real) == 2 and sum(g.artefact for g in comp.segments) == 2
    got = sorted(np.round(g.centroid, 2).tolist() for g in real)
    want = sorted(np.round(b.mean(axis=0), 2).tolist() for b in blobs)
    np.testing.assert_allclose(got, want, atol=0.01)
    assert all(g.size == 200 and g.kind == "new" and g.mean_score == 50.0 for g in real)
    assert sorted(len(v) for g in real for v in g.members.values()) == [200, 200]
    assert notes["segments"] == {"new": 2, "removed": 0, "artefacts": 2}


def test_segments_round_trip_through_the_twin(tmp_path) -> None:
    from pxr import Usd

    from twin_store import Segment, TwinStore

    store = TwinStore.create(tmp_path / "twin")
    seg = Segment(id=3, kind="new", centroid=np.array([1.0, 2.0, 3.0]), lower=np.array([0.5, 1.5, 2.5]),
                  upper=np.array([1.5, 2.5, 3.5]), mean_score=12.5, size=40, artefact=False,
                  members={"E1_scan": np.arange(40)})
    store.write_epoch("E1", [], {}, segments=[seg])
    (back,) = store.read_segments("E1")
    assert back.id == 3 and back.kind == "new" and back.size == 40 and not back.artefact and back.part is None
    np.testing.assert_allclose(back.centroid, [1, 2, 3])
    np.testing.assert_array_equal(back.members["E1_scan"], np.arange(40))
    assert store.read_segments("E1", members=False)[0].members == {}
    stage = Usd.Stage.Open(str(tmp_path / "twin" / "twin.usda"))  # held: a prim dies with its stage
    prim = stage.GetPrimAtPath("/Segments/E1/seg_0003")
    assert prim and prim.GetAttribute("gdt:meanScore").Get() == 12.5


def test_each_element_records_why_it_is_in_the_composite_and_the_twin_keeps_it(registry, scene, tmp_path) -> None:
    from pxr import Usd, UsdGeom

    from gdt_pipeline import FusionReason
    from gdt_pipeline.twin_elements import composite_to_elements
    from twin_store import REASON_NAMES, TwinStore

    reference, precise, change = scene
    comp, notes = _run(registry, "most_reliable", reference, [precise], [change])
    items = {it.key: it for it in comp.items}
    tof, sl, cad = items["E1_tof"], items["E2_sl"], items["E0_cad"]
    on_tof = precise.points[:, 0] > 1.05
    on_cad = precise.points[:, 0] < 0.95
    # the 1 cm scan went because the 0.1 mm scan is more precise: √det Σ ratio (1e-4 / 1e-2)³ = 1e-6
    gone = tof.reason == FusionReason.REPLACED
    assert np.array_equal(gone, ~tof.visible) and gone.sum() >= 2970
    np.testing.assert_allclose(tof.reason_ratio[gone], 1e-6, rtol=1e-9)
    assert np.isnan(tof.reason_ratio[~gone]).all() and (tof.reason[~gone] == FusionReason.KEPT).all()
    assert (sl.reason[on_tof] == FusionReason.REPLACES).mean() > 0.99
    np.testing.assert_allclose(sl.reason_ratio[on_tof & (sl.reason == FusionReason.REPLACES)], 1e-6, rtol=1e-9)
    assert (sl.reason[on_cad] == FusionReason.DESIGN_STAYS).all() and (cad.reason == FusionReason.KEPT).all()
    assert notes["reasons"]["replaced"] == gone.sum()
    # keep_unchanged: the known data stays, the precise scan is hidden by policy
    comp_k, _ = _run(registry, "keep_unchanged", reference, [precise], [change])
    assert (comp_k.items[-1].reason == FusionReason.KNOWN_STAYS).all()
    # the reasons and ratios are per-element primvars of the epoch layer, read back by pxr and by the store
    store = TwinStore.create(tmp_path / "twin")
    store.write_epoch("E2", composite_to_elements(comp), {})
    stage = Usd.Stage.Open(str(tmp_path / "twin" / "twin.usda"))  # held: a prim dies with its stage
    prim = stage.GetPrimAtPath("/Twin/E1_tof")
    codes = np.asarray(UsdGeom.PrimvarsAPI(prim).GetPrimvar("gdt:fusionReason").Get())
    assert np.array_equal(codes, tof.reason) and REASON_NAMES[FusionReason.REPLACED] == "replaced"
    back = {es.key: es for es in store.read_epoch("E2")}
    np.testing.assert_array_equal(back["E2_sl"].reason, sl.reason)
    np.testing.assert_allclose(back["E1_tof"].reason_ratio, tof.reason_ratio.astype(np.float32))
    assert all(name.upper() == FusionReason(i).name for i, name in enumerate(REASON_NAMES))


def test_a_point_item_is_made_for_the_writer_a_run_of_rows_at_a_time(registry, scene) -> None:
    from gdt_pipeline.twin_elements import composite_to_elements
    from twin_store import RowsOnDemand, whole
    from twin_store.elements import PER_ELEMENT

    reference, precise, change = scene
    comp, _ = _run(registry, "most_reliable", reference, [precise], [change])
    kinds = []
    for source in composite_to_elements(comp):
        es = whole(source)
        kinds.append((es.kind, isinstance(source, RowsOnDemand)))
        if es.kind == "mesh":
            continue
        # a middle run of rows is the whole set's rows, field by field (covariances packed from the rows' own)
        start, stop = es.n_elements // 3, 2 * es.n_elements // 3
        part = source.rows(start, stop)
        assert part.n_elements == stop - start and part.key == es.key
        for name in PER_ELEMENT:
            if getattr(es, name) is None:
                assert getattr(part, name) is None, name
            else:
                np.testing.assert_array_equal(getattr(part, name), np.asarray(getattr(es, name))[start:stop], name)
    assert sorted(set(kinds)) == [("mesh", False), ("points", True)]


def _bracket_scan(sweep: bool) -> tuple[np.ndarray, np.ndarray]:
    """Structured-light points on one new bracket of the fuselage scene: from the six overview stations, or with the
    handheld sweep along its web; and the bracket's solid centre."""
    from gdt_pipeline.simulation import ScannerSpec, simulate_scan
    from gdt_pipeline.simulation.fuselage import WEB_ANGLES_DEG, fuselage_objects, station, web_station

    objects = fuselage_objects()
    present = [n for n in objects if n != "bracket_removed"]
    meshes = [objects[n][0] for n in present]
    stations = [station(x, deg, 0.9) for x in (0.53, 1.07) for deg in (-28.0, 0.0, 28.0)]
    if sweep:
        stations += [web_station(1, +1, deg) for deg in WEB_ANGLES_DEG]  # bracket_new_3 sits at frame 1, side +1
    spec = ScannerSpec(profile="structured_light", points_per_m2=40000.0, fov_deg=60.0, max_range=3.0)
    rng = np.random.default_rng(3)
    k = present.index("bracket_new_3")
    pts = []
    for eye, target in stations:
        scan = simulate_scan(meshes, eye, target, spec, rng)
        pts.append(scan.points[scan.object_id == k])
    return np.vstack(pts), objects["bracket_new_3"][0].center_mass


def test_a_catalogue_part_fitted_to_a_new_segment_gives_its_centre(registry, scene, tmp_path) -> None:
    from pathlib import Path

    from gdt_pipeline.simulation.fuselage import bracket_part
    from stages.fusion.parts import fit_part, load_part
    from twin_store import TwinStore

    part_path = Path(tmp_path / "bracket.obj")
    bracket_part().export(part_path)
    part = load_part("bracket", part_path, None, seed=0)
    np.testing.assert_allclose(part.centre, 0.0, atol=1e-9)
    swept, centre = _bracket_scan(sweep=True)
    fit = fit_part(swept, part, np.random.default_rng(0))
    # the model fitted to a sweep that sees the bracket's plate, leg and ends gives its solid centre to < 1 mm
    assert fit.accepted and not fit.ambiguous and fit.rms < 3e-4 and fit.fitness > 0.99
    assert np.linalg.norm(fit.centre - centre) < 1e-3
    assert np.linalg.norm(swept.mean(axis=0) - centre) > 3e-3  # what was measured is not the part's centre
    # six stations 0.9 m away see one face: the model fits in several places as well, and the fit says so
    one_sided, _ = _bracket_scan(sweep=False)
    fit = fit_part(one_sided, part, np.random.default_rng(0))
    assert fit.ambiguous and not fit.accepted and fit.rms < 3e-4
    # through the fusion stage: the segment records the part, and the twin keeps it
    reference, _, _ = scene
    new = _gauss(swept, 1e-4, "sl")
    n = new.n_elements
    change = Change(query=0, score=np.full(n, 50.0), mask=np.ones(n, bool), state=np.full(n, 1, np.uint8))
    comp, notes = _run(registry, "keep_unchanged", reference, [new], [change],
                       parts=[{"name": "bracket", "path": str(part_path)}], segment_radius=0.01)
    (seg,) = [g for g in comp.segments if not g.artefact]
    assert seg.part == "bracket" and np.linalg.norm(seg.part_centre - centre) < 1e-3 and seg.fit_rms < 3e-4
    assert notes["parts"]["segments"][0]["fitted"] == "bracket"
    assert len(notes["parts"]["models"]["bracket"]["sha256"]) == 64
    store = TwinStore.create(tmp_path / "twin")
    store.write_epoch("E2", [], {}, segments=comp.segments)
    back = next(g for g in store.read_segments("E2") if not g.artefact)
    assert back.part == "bracket" and back.fit_rms == pytest.approx(seg.fit_rms)
    np.testing.assert_allclose(back.part_centre, seg.part_centre)
    np.testing.assert_allclose(back.part_pose, seg.part_pose)
    with pytest.raises(ValueError, match="no model file"):
        _run(registry, "keep_unchanged", reference, [new], [change], parts=[{"name": "x", "path": "/nope.obj"}])


def test_segments_one_fitted_part_explains_become_one(registry, scene, tmp_path) -> None:
    # a radius below the gap where the leg hides the corner parts the bracket; its model fitted to the pieces
    # together joins them into one segment with the part's centre
    from gdt_pipeline.simulation.fuselage import bracket_part

    part_path = tmp_path / "bracket.obj"
    bracket_part().export(part_path)
    swept, centre = _bracket_scan(sweep=True)
    reference, _, _ = scene
    new = _gauss(swept, 1e-4, "sl")
    n = new.n_elements
    change = Change(query=0, score=np.full(n, 50.0), mask=np.ones(n, bool), state=np.full(n, 1, np.uint8))
    split, _ = _run(registry, "keep_unchanged", reference, [new], [change], segment_radius=0.004)
    pieces = [g for g in split.segments if not g.artefact]
    assert len(pieces) >= 2
    comp, notes = _run(registry, "keep_unchanged", reference, [new], [change], segment_radius=0.004,
                       parts=[{"name": "bracket", "path": str(part_path)}])
    real = [g for g in comp.segments if not g.artefact]
    assert len(real) == 1 and real[0].part == "bracket"
    assert real[0].size >= sum(g.size for g in pieces)
    assert np.linalg.norm(real[0].part_centre - centre) < 1e-3
    assert [g.id for g in comp.segments] == list(range(len(comp.segments)))
    assert notes["parts"]["segments"][0]["joined_sizes"]


def test_spread_in_pieces_gives_every_element_its_own_volume_and_largest_sigma(monkeypatch: pytest.MonkeyPatch
                                                                                ) -> None:
    import stages.fusion._segments as segments_module

    rng = np.random.default_rng(23)
    n = 1000
    sig = rng.uniform(0.001, 0.02, (n, 3))
    rot = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
    cov = rot @ (sig[:, :, None] ** 2 * np.eye(3)[None]) @ np.swapaxes(rot, 1, 2)
    ds = Dataset(name="c", role="as-is", points=rng.normal(size=(n, 3)), uncertainty=GaussianUncertainty(cov))
    idx = rng.choice(n, 700, replace=False)
    monkeypatch.setattr(segments_module, "SPREAD_PIECE", 64)  # eleven pieces, the last one short
    volume, largest = segments_module.spread(ds, idx)
    assert np.allclose(volume, np.prod(sig[idx], axis=1), rtol=1e-9)  # √det Σ = σ1 σ2 σ3 whatever the rotation
    assert np.allclose(largest, sig[idx].max(axis=1), rtol=1e-9)


@pytest.mark.parametrize("policy", ["most_reliable", "replace_in_view"])
def test_fusion_in_pieces_decides_every_element_as_in_one_piece(registry, scene, policy: str,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    import stages.fusion._replace as replace_module

    reference, precise, change = scene
    whole, _ = _run(registry, policy, reference, [precise], [change])
    monkeypatch.setattr(replace_module, "CHOOSE_PIECE", 701)  # nine pieces, the last one short
    pieces, notes = _run(registry, policy, reference, [precise], [change])
    assert notes["fusion"]["replaced"].get("E1_tof", 0) >= 2970  # the measured scan's path is taken, not only the CAD
    for a, b in zip(whole.items, pieces.items, strict=True):
        for name in ("visible", "state", "reason"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), (a.key, name)
        assert np.array_equal(a.reason_ratio, b.reason_ratio, equal_nan=True), a.key
