"""E57 scans with their station poses: one dataset per scan in the file's frame, its station from the header for
every stage (no ``viewpoints:`` needed), intensity and colour carried, damaged files refused; and the one order of
pose sources (pose file, file header, ``viewpoints:``) recorded in the provenance."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import plyfile
import pye57
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from gdt_pipeline import InputError
from gdt_pipeline.audit import audit_twin
from gdt_pipeline.runner import read_datasets, run_workflow
from gdt_pipeline.simulation.scanner import ScannerSpec, simulate_scan
from gdt_pipeline.simulation.suite_workflow import STAGES
from twin_store import TwinStore

STATIONS = (  # (name, eye, target, yaw of the scanner's frame in degrees)
    ("north", (0.2, 3.0, 1.4), (0.0, 0.0, 0.5), 75.0),
    ("east", (3.2, -0.6, 1.1), (0.2, 0.0, 0.4), -20.0),
)

HEADER = """\
name: e57
twin: {twin}
seed: 11
epochs:
  - id: E0
    role: as-designed
    inputs: [{{path: cad.obj}}]
  - id: E1
    role: as-is
    inputs: [{inputs}]
"""


def workflow(twin: str, inputs: str) -> str:
    """The suite scenes' default chain (the tof_low_cost preset) over the CAD cube and the given E1 inputs."""
    return HEADER.format(twin=twin, inputs=inputs) + STAGES.replace("PROFILE", "tof_low_cost")


def _quaternion_wxyz(rot: Rotation) -> np.ndarray:
    x, y, z, w = rot.as_quat()
    return np.array([w, x, y, z])


def _write_e57(path: Path, scans: list[tuple[str, np.ndarray, np.ndarray, Rotation]],
               intensity: bool = True) -> None:
    """Scans in their own frames (world = R·local + t), each with its pose, as E57 through pye57's writer."""
    with pye57.E57(str(path), mode="w") as e57:
        for name, world, eye, rot in scans:
            local = rot.inv().apply(world - eye)
            data = {"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2]}
            if intensity:
                data["intensity"] = np.linspace(0.1, 0.9, len(local))
                for k, c in enumerate(("colorRed", "colorGreen", "colorBlue")):
                    data[c] = ((np.arange(len(local)) * (k + 3)) % 256).astype(np.uint8)
            e57.write_scan_raw(data, name=name, rotation=_quaternion_wxyz(rot), translation=np.asarray(eye, float))


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CAD cube, and two ToF stations scanning it with a new box beside it, written as one E57."""
    root = tmp_path_factory.mktemp("e57scene")
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cube.apply_translation((0, 0, 0.5))
    cube.export(root / "cad.obj")
    new = trimesh.creation.box(extents=(0.3, 0.3, 0.3))
    new.apply_translation((1.0, 0.0, 0.15))
    spec = ScannerSpec(profile="tof_low_cost", fov_deg=50.0, aspect=1.2, points_per_m2=6000.0, max_range=8.0)
    rng = np.random.default_rng(5)
    scans = []
    for name, eye, target, yaw in STATIONS:
        shot = simulate_scan([cube, new], np.asarray(eye), np.asarray(target), spec, rng)
        scans.append((name, shot.points, np.asarray(eye, float), Rotation.from_euler("zx", [yaw, 4.0], degrees=True)))
    _write_e57(root / "stations.e57", scans)
    return root


def test_every_scan_is_a_dataset_in_the_files_frame_with_its_station(scene: Path, registry: object) -> None:
    parts = read_datasets(scene / "stations.e57", registry, name="stations")
    assert [p.name for p in parts] == ["stations_north", "stations_east"]
    for part, (name, eye, _, yaw) in zip(parts, STATIONS, strict=True):
        rot = Rotation.from_euler("zx", [yaw, 4.0], degrees=True)
        assert part.pose is not None and part.pose.source == "file_header"
        assert np.allclose(part.pose.position, eye, atol=1e-12)
        assert np.allclose(part.pose.rotation, rot.as_matrix(), atol=1e-9)
        assert part.meta["name"] == name and part.meta["guid"].startswith("{")
        # the points come back in the file's frame: the station looked at the cube near the origin
        assert np.linalg.norm(part.points.mean(axis=0) - np.array([0.3, 0.0, 0.5])) < 1.0
        assert part.fields["intensity"].shape == (len(part.points),)
        assert np.allclose(part.fields["intensity"][[0, -1]], [0.1, 0.9], atol=1e-6)
        expected = ((np.arange(len(part.points)) * 3) % 256) / 255.0
        assert np.allclose(part.fields["color"][:, 0], expected, atol=1e-6)


def test_a_workflow_without_viewpoints_equals_the_one_given_them_by_hand(scene: Path, registry: object,
                                                                        tmp_path: Path) -> None:
    parts = read_datasets(scene / "stations.e57", registry, name="stations")
    hand = tmp_path / "hand"
    hand.mkdir()
    (hand / "cad.obj").write_bytes((scene / "cad.obj").read_bytes())
    inputs = []
    for part in parts:  # the same points, as plain PLY files, and the stations typed in by hand
        vertex = np.empty(len(part.points), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
        vertex["x"], vertex["y"], vertex["z"] = part.points.T
        plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(hand / f"{part.name}.ply"))
        vp = ", ".join(repr(float(v)) for v in part.pose.position)
        inputs.append(f"{{path: {part.name}.ply, name: {part.name}, viewpoints: [[{vp}]]}}")
    (hand / "workflow.yaml").write_text(textwrap.dedent(workflow(twin="twin", inputs=", ".join(inputs))))
    (scene / "workflow.yaml").write_text(textwrap.dedent(workflow(twin=str(tmp_path / "twin_e57"),
                                                                        inputs="{path: stations.e57}")))
    by_header = run_workflow(scene / "workflow.yaml", registry=registry, twin=tmp_path / "twin_e57").twin
    by_hand = run_workflow(hand / "workflow.yaml", registry=registry).twin
    sets_header = {es.key: es for es in TwinStore.open(by_header).read_epoch("E1")}
    sets_hand = {es.key: es for es in TwinStore.open(by_hand).read_epoch("E1")}
    assert sorted(sets_header) == sorted(sets_hand) == ["E0_cad", "E1_stations_east", "E1_stations_north"]
    for key, es in sets_header.items():
        other = sets_hand[key]
        assert np.array_equal(es.points, other.points)
        assert np.array_equal(es.state, other.state) and np.array_equal(es.visible, other.visible)
        assert np.array_equal(es.score, other.score, equal_nan=True)
        assert np.array_equal(es.covariance, other.covariance)
    scan = sets_header["E1_stations_north"]
    assert np.sum(scan.state == 1) > 50  # the new box was found
    assert sets_header["E1_stations_north"].intensity is not None and sets_hand["E1_stations_north"].intensity is None
    prov = TwinStore.open(by_header).provenance("E1")["inputs"][0]
    assert [d["pose"]["source"] for d in prov["datasets"]] == ["file_header", "file_header"]
    assert prov["datasets"][0]["pose"]["position"] == list(STATIONS[0][1])
    hand_prov = TwinStore.open(by_hand).provenance("E1")["inputs"][0]
    assert hand_prov["datasets"][0]["pose"]["source"] == "workflow"
    audit = audit_twin(by_header, registry=registry)  # the E57 read again as recorded: its scans, poses and units
    assert audit.ok and [e.verdict for e in audit.epochs] == ["match", "match"]


def test_a_pose_file_comes_first_and_a_disagreeing_viewpoint_is_recorded(registry: object, tmp_path: Path) -> None:
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cube.export(tmp_path / "cad.obj")
    pts = trimesh.sample.sample_surface(cube, 2000, seed=1)[0]
    vertex = np.array([tuple(p) for p in pts], dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(tmp_path / "scan.ply"))
    (tmp_path / "scan_pose.json").write_text(json.dumps({"viewpoint": [2.0, 0.0, 0.0]}))
    inputs = "{path: scan.ply, name: scan, viewpoints: [[0.0, 3.0, 0.0]]}"
    text = workflow(twin="twin", inputs=inputs).replace("  - uses: sensor_frustum\n    role: as-is\n", "")
    text = text.replace("calibrated_threshold\n    role: as-is\n    with: {false_alarm: 0.01}",
                        "fixed\n    role: as-is\n    with: {tau: 10}")
    (tmp_path / "workflow.yaml").write_text(text.replace("most_reliable", "keep_unchanged"))
    twin = run_workflow(tmp_path / "workflow.yaml", registry=registry).twin
    record = TwinStore.open(twin).provenance("E1")["inputs"][0]["datasets"][0]
    assert record["pose"]["source"] == "pose_file" and record["pose"]["position"] == [2.0, 0.0, 0.0]
    assert "differ from the pose file" in record["pose_warning"]
    # the pose file alone is enough for sensor_model (it used to stop asking for `viewpoints:`), with the same result
    (tmp_path / "alone.yaml").write_text(text.replace("most_reliable", "keep_unchanged").replace(
        ", viewpoints: [[0.0, 3.0, 0.0]]", "").replace("twin: twin", "twin: alone"))
    alone = run_workflow(tmp_path / "alone.yaml", registry=registry).twin
    (with_vp,), (without,) = (TwinStore.open(t).read_epoch("E1", ["E1_scan"]) for t in (twin, alone))
    assert np.array_equal(with_vp.covariance, without.covariance) and np.array_equal(with_vp.state, without.state)
    assert "pose_warning" not in TwinStore.open(alone).provenance("E1")["inputs"][0]["datasets"][0]


def test_damaged_e57_files_are_errors_never_points(scene: Path, registry: object, tmp_path: Path) -> None:
    whole = (scene / "stations.e57").read_bytes()
    cut = tmp_path / "cut.e57"
    cut.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(InputError, match=r"cut\.e57.*not a readable E57 file"):
        read_datasets(cut, registry, name="cut")
    flipped = bytearray(whole)
    flipped[len(whole) // 3] ^= 0xFF  # one byte of point data: libE57Format's page checksum must catch it
    bad = tmp_path / "flipped.e57"
    bad.write_bytes(bytes(flipped))
    with pytest.raises(InputError, match=r"flipped\.e57.*the file is damaged: checksum mismatch"):
        read_datasets(bad, registry, name="bad")
    text = tmp_path / "text.e57"
    text.write_text("not an e57 file\n" * 100)
    with pytest.raises(InputError, match=r"text\.e57.*not a readable E57 file"):
        read_datasets(text, registry, name="text")


def test_scans_can_be_chosen_and_a_pose_file_cannot_serve_several(scene: Path, registry: object,
                                                                  tmp_path: Path) -> None:
    from gdt_pipeline.plugins import ReadRequest

    spec = registry.reader("pye57_scans")
    request = ReadRequest(scene / "stations.e57", "s", "as-is", None, "", params=spec.params(scans=[1]))
    (only,) = spec.read(request)
    assert only.name == "east" and request.notes["scans"] == 1
    with pytest.raises(InputError, match=r"scans \[5\] asked for, but the file holds 2"):
        spec.read(ReadRequest(scene / "stations.e57", "s", "as-is", None, "", params=spec.params(scans=[5])))
    copy = tmp_path / "two.e57"
    copy.write_bytes((scene / "stations.e57").read_bytes())
    (tmp_path / "two_pose.json").write_text(json.dumps({"viewpoint": [0, 0, 0]}))
    from gdt_pipeline.runner import resolve_poses

    with pytest.raises(InputError, match=r"two_pose\.json states one station but the file holds 2 datasets"):
        resolve_poses(read_datasets(copy, registry, name="two"), copy, None, 1.0, "here")


def test_reader_parameters_come_from_the_inputs_with(scene: Path, registry: object, tmp_path: Path) -> None:
    from gdt_pipeline.workflow import WorkflowError, load_workflow

    text = workflow(twin=str(tmp_path / "one"), inputs="{path: stations.e57, with: {scans: [1]}}")
    (scene / "one.yaml").write_text(textwrap.dedent(text))
    twin = run_workflow(scene / "one.yaml", registry=registry).twin
    assert [es.key for es in TwinStore.open(twin).read_epoch("E1")] == ["E0_cad", "E1_stations_east"]
    record = TwinStore.open(twin).provenance("E1")["inputs"][0]
    assert record["params"] == {"scans": [1]} and [d["name"] for d in record["datasets"]] == ["stations_east"]
    (scene / "bad.yaml").write_text(textwrap.dedent(workflow(
        twin="t", inputs="{path: stations.e57, with: {scan: [1]}}")))
    with pytest.raises(WorkflowError, match=r"epochs\.1\.inputs\.0\.with\.scan: reader 'pye57_scans': Extra inputs"):
        load_workflow(scene / "bad.yaml", registry)
