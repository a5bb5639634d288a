"""Moved parts: a removed part of the twin whose own model fits a new segment is recorded as moved, with its
displacement, and the record survives the twin's USD."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh
from pxr import Usd

from gdt_pipeline import CompositeItem, Dataset, EpochInfo, GaussianUncertainty, Segment
from gdt_pipeline.plugins import StageContext, load_registry
from stages.fusion._moved import moved
from twin_store import guides


@pytest.fixture(scope="module")
def registry():
    return load_registry()


def _ctx(registry) -> StageContext:
    spec = registry.get("most_reliable")
    info = EpochInfo(id="E1", index=1, role="as-is", seed=0, workflow_dir=".", units="m")
    return StageContext(stage=spec, params=spec.params(), slots={"epoch": info}, epoch=info,
                        rng=np.random.default_rng(0), seed=0, log=logging.getLogger("test"))


def _segment(sid: int, kind: str, key: str, pos: np.ndarray) -> Segment:
    return Segment(id=sid, kind=kind, centroid=pos.mean(axis=0), lower=pos.min(axis=0), upper=pos.max(axis=0),
                   mean_score=1.0, size=len(pos), artefact=False, members={key: np.arange(len(pos))})


def test_a_part_seen_at_a_new_place_is_recorded_as_moved(registry) -> None:
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.4))
    box.apply_translation((0.0, 0.0, 0.2))
    shift = np.array([0.25, -0.12, 0.0])
    # what a scan of the moved box shows: its top and the two sides facing a sensor, 2 mm noise
    pts, face = trimesh.sample.sample_surface(box, 6000, seed=1)
    seen = (box.face_normals[face] @ np.array([1.0, -1.0, 1.0])) > 0.5
    rng = np.random.default_rng(2)
    scan = pts[seen] + shift + rng.normal(0, 0.002, (int(seen.sum()), 3))
    n = len(box.faces)
    cad = CompositeItem("E0_cad_box", Dataset("cad_box", "as-designed", box.vertices, faces=box.faces), "E0",
                        np.full(n, 2, np.uint8), np.full(n, np.nan), np.zeros(n, np.int32), np.zeros(n, bool))
    cov = np.broadcast_to(np.eye(3) * 4e-6, (len(scan), 3, 3))
    ds = Dataset("scan", "as-is", scan).with_uncertainty(GaussianUncertainty(cov))
    recent = CompositeItem("E1_scan", ds, "E1", np.ones(len(scan), np.uint8), np.zeros(len(scan)),
                           np.ones(len(scan), np.int32), np.ones(len(scan), bool))
    other = trimesh.creation.box(extents=(0.05, 0.05, 0.05)).sample(500) + np.array([1.0, 1.0, 0.0])
    found = [_segment(0, "new", "E1_scan", scan), _segment(1, "new", "E1_scan", other),
             _segment(2, "removed", "E0_cad_box", box.triangles_center)]
    out = moved(_ctx(registry), [cad, recent], found)
    rec = out[0]
    assert rec.moved_from == 2 and rec.moved_item == "E0_cad_box"
    assert np.linalg.norm(rec.displacement - shift) < 0.005
    # a box fits itself turned by 180° as well: the angle is one of its symmetries
    assert min(rec.rotation_deg, abs(180.0 - rec.rotation_deg)) < 2.0
    assert out[1].moved_from is None  # a small new part is no box of that size


def test_the_moved_record_is_written_and_read_back_with_usd() -> None:
    stage = Usd.Stage.CreateInMemory()
    seg = Segment(id=3, kind="new", centroid=np.array([1, 2, 3]), lower=np.zeros(3), upper=np.ones(3),
                  mean_score=9.0, size=40, artefact=False, members={"E1_scan": np.arange(4)}, moved_from=5,
                  moved_item="E0_cad_box", displacement=np.array([0.25, -0.12, 0.0]), rotation_deg=1.5)
    guides.define_segment(stage, "E1", seg)
    back = guides.read_segments(stage, "E1")[0]
    assert back.moved_from == 5 and back.moved_item == "E0_cad_box" and back.rotation_deg == 1.5
    assert np.allclose(back.displacement, [0.25, -0.12, 0.0])


def test_moved_records_are_scored_against_the_true_displacements() -> None:
    from gdt_pipeline.evaluation.suite_scoring import moved_scores

    def seg(k: int, item: str | None, shift: list[float] | None) -> Segment:
        return Segment(id=k, kind="new", centroid=np.zeros(3), lower=np.zeros(3), upper=np.ones(3), mean_score=9.0,
                       size=40, artefact=False, moved_item=item,
                       displacement=None if shift is None else np.array(shift))

    segments = [seg(0, "E0_cad_box_3", [0.2, 0.0, 0.001]), seg(1, "E0_cad_pipe_1", [0.0, 0.1, 0.0]),
                seg(2, None, None)]
    out = moved_scores({"box_3": [0.2, 0.0, 0.0], "panel_2": [0.0, 0.05, 0.0]}, segments)
    assert out["parts"]["box_3"] == {"recorded": True, "error_mm": 1.0}
    assert out["parts"]["panel_2"] == {"recorded": False, "error_mm": None}
    assert out["wrong_records"] == ["E0_cad_pipe_1"]


def test_gdt_log_lists_the_moved_parts() -> None:
    from gdt_pipeline.cli.twin_commands import moved_lines

    def seg(k: int, **moved: object) -> Segment:
        return Segment(id=k, kind="new", centroid=np.zeros(3), lower=np.zeros(3), upper=np.ones(3), mean_score=9.0,
                       size=40, artefact=False, **moved)

    class Store:
        def read_segments(self, epoch_id: str, *, members: bool = True) -> list[Segment]:
            return [seg(0), seg(2, moved_item="E0_cad_box", moved_from=7, displacement=np.array([0.3, -0.4, 0.0]),
                            rotation_deg=0.5)]

    assert moved_lines(Store(), "E1") == ["E1: E0_cad_box moved by 0.5 (0.3, -0.4, 0), turned 0.5°; new segment 2, "
                                          "removed segment 7"]
