"""The records' own operations, each in one place: a field added to ``Correspondences`` is carried by a stage call's
sorting, a tile's crop and the merge of tiles without more code; the uncertainty models rotate, repeat and
moment-match as their closed forms say; a pose file's scanner geometry is typed and checked when it is read."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gdt_pipeline import BoxUncertainty, Correspondences, GaussianUncertainty, InputError, MixtureUncertainty
from gdt_pipeline.runner.poses import read_pose_file
from gdt_pipeline.runner.stage_call import element_ordered
from gdt_pipeline.tiling import merge_correspondences, take_candidates
from gdt_pipeline.types.correspondences import PER_CANDIDATE


@dataclass(frozen=True)
class Tagged(Correspondences):
    """Correspondences with one more per-candidate field, as a later change might add."""

    tag: np.ndarray | None = field(default=None, metadata=PER_CANDIDATE)


def _tagged(rng: np.random.Generator, m: int, n: int) -> Tagged:
    element = rng.integers(0, n, m)
    return Tagged(0, rng.integers(0, 2, m), rng.integers(0, 50, m), rng.normal(size=(m, 3)), rng.uniform(size=m),
                  "test", element=element, n_elements=n, query_position=rng.normal(size=(m, 3)),
                  query_uncertainty=GaussianUncertainty.isotropic(rng.uniform(0.001, 0.01, m)),
                  tag=np.arange(m) * 10 + 7)


def test_a_new_per_candidate_field_survives_stage_calls_crops_and_merges() -> None:
    rng = np.random.default_rng(11)
    corr = _tagged(rng, 80, 30)
    ordered = element_ordered(corr)  # what every stage call does to the correspondences it returns
    assert isinstance(ordered, Tagged) and np.all(np.diff(ordered.element) >= 0)
    order = np.argsort(corr.element, kind="stable")
    assert np.array_equal(ordered.tag, corr.tag[order])
    assert np.array_equal(ordered.query_uncertainty.cov, corr.query_uncertainty.cov[order])
    # two tiles of even and odd elements, each keeping its own candidates, then merged back
    same = [lambda e: e, lambda e: e]
    parts = [take_candidates(ordered, ordered.element % 2 == k, lambda e: e, same, 30) for k in (0, 1)]
    assert all(isinstance(p, Tagged) for p in parts)
    for k, part in enumerate(parts):
        assert np.array_equal(part.tag, ordered.tag[ordered.element % 2 == k])
    merged, _ = merge_correspondences(parts, 30, 0)
    assert isinstance(merged, Tagged)
    for name in ("tag", "element", "ref_element", "position", "query_position"):
        assert np.array_equal(getattr(merged, name), getattr(ordered, name)), name
    assert np.array_equal(merged.query_uncertainty.cov, ordered.query_uncertainty.cov)
    mixed = [parts[0], dataclasses.replace(parts[1], tag=None)]
    with pytest.raises(Exception, match="tag"):  # tiles that disagree are an error naming the field
        merge_correspondences(mixed, 30, 0)


def test_models_rotate_repeat_and_moment_match_as_their_closed_forms_say() -> None:
    rot = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    cov = np.diag([1e-4, 4e-4, 9e-4])
    g = GaussianUncertainty(cov[None])
    assert np.allclose(g.rotated(rot).cov[0], rot @ cov @ rot.T)
    box = BoxUncertainty(np.array([[0.01, 0.02, 0.03]]))
    turned = box.rotated(rot)
    assert np.allclose(turned.covariance(1)[0], rot @ box.covariance(1)[0] @ rot.T)  # R diag(h²/3) Rᵀ
    mix = MixtureUncertainty(np.array([[0.5, 0.5]]), np.array([[[0.01, 0, 0], [-0.01, 0, 0]]]),
                             np.broadcast_to(cov, (1, 2, 3, 3)))
    # the moments of the turned mixture are the turned moments (about the mixture's own mean)
    assert np.allclose(mix.rotated(rot).covariance(1)[0], rot @ mix.covariance(1)[0] @ rot.T)
    assert np.allclose(mix.moment_matched(1).cov[0], cov + np.diag([1e-4, 0, 0]))  # + the spread of the means
    assert box.moment_matched(4).rows == 4 and g.moment_matched(4) is g
    assert box.repeated(3).rows == 3 and np.array_equal(box.repeated(3).half_widths[2], box.half_widths[0])
    assert g.stored(2)["covariance"].tolist() == [[1e-4, 0, 0, 4e-4, 0, 9e-4]] * 2  # the twin's xx xy xz yy yz zz


def test_a_pose_files_scanner_is_typed_and_checked(tmp_path: Path) -> None:
    pose = tmp_path / "s_pose.json"
    pose.write_text(json.dumps({"viewpoint": [0, 0, 1], "target": [1, 0, 1],
                                "scanner": {"kind": "pinhole", "fov_deg": 60, "aspect": 1.5, "max_range": 4.0,
                                            "points_per_m2": 2e4, "profile": "tof_low_cost"}}))
    scanner = read_pose_file(pose).scanner
    assert scanner is not None and scanner.pinhole_frustum
    assert (scanner.fov_deg, scanner.aspect, scanner.max_range, scanner.min_range) == (60.0, 1.5, 4.0, None)
    assert read_pose_file(pose).scaled(0.001).scanner.max_range == pytest.approx(0.004)  # mm file, m twin
    pose.write_text(json.dumps({"viewpoint": [0, 0, 1], "scanner": {"fov_deg": "wide"}}))
    with pytest.raises(InputError, match=r"s_pose\.json: scanner 'fov_deg' must be a finite number, not 'wide'"):
        read_pose_file(pose)
    pose.write_text(json.dumps({"viewpoint": [0, 0, 1], "scanner": [60, 1.5]}))
    with pytest.raises(InputError, match=r"s_pose\.json: 'scanner' must be a mapping"):
        read_pose_file(pose)
    pose.write_text(json.dumps({"viewpoint": [0, 0, 1], "scanner": {"kind": "spherical", "fov_deg": 360}}))
    assert not read_pose_file(pose).scanner.pinhole_frustum  # no frustum to build from a spherical scanner
