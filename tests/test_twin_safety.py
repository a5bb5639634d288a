"""Issue-18 safety of the twin as users meet it: a damaged layer is named (sha256 recorded and actual), never read
as data; a damaged or missing gdt.lock is reported; --overwrite never deletes the user's files; a refused writer
leaves the holder's lock record; what a killed swap left behind is put back or reported."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gdt_pipeline.runner import run_workflow
from twin_store import TwinStore, TwinStoreError, lock_path, swap_into_place, writer_lock
from twin_store.swap import exchange

from .conftest import CubeScene, holding_writer_lock, make_cube_scene, run_gdt, write_cube_workflow


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory, registry) -> CubeScene:
    """A small cube scene with its two-epoch twin, written once; tests work on copies."""
    scene = make_cube_scene(tmp_path_factory.mktemp("safety") / "scene", n_cube=1500, n_new=300)
    run_workflow(write_cube_workflow(scene), registry=registry)
    return scene


@pytest.fixture
def scene(template: CubeScene, tmp_path: Path) -> CubeScene:
    """A private copy of the template scene and twin."""
    root = tmp_path / "scene"
    shutil.copytree(template.dir, root)
    return CubeScene(root, root / template.cad.name, root / template.scan.name, template.changed, template.sigma)


def _layers(twin: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((twin / "epochs").iterdir())}


def _flip(path: Path, offset: int, n: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset:offset + n] = bytes(b ^ 0x5A for b in data[offset:offset + n])
    path.write_bytes(bytes(data))


def _failed(res: subprocess.CompletedProcess, *needles: str) -> str:
    err = " ".join(res.stderr.split())
    assert res.returncode == 1, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr and "internal error" not in err
    for needle in needles:
        assert needle in err, err
    return err


def test_flipped_bytes_in_a_layer_are_named_by_log_show_and_audit(scene: CubeScene) -> None:
    twin = scene.dir / "twin"
    layer = twin / "epochs" / "E1.usdc"
    recorded = TwinStore.open(twin).layer_digests()["epochs/E1.usdc"]
    _flip(layer, len(layer.read_bytes()) // 2, 64)
    for command in (["log", str(twin)], ["show", str(twin)], ["show", str(twin), "--epoch", "E1"],
                    ["audit", str(twin)]):
        _failed(run_gdt(*command), "E1.usdc", "corrupted", f"recorded {recorded}")
    # an earlier epoch composes without the damaged layer, so it still reads
    assert run_gdt("show", str(twin), "--epoch", "E0").returncode == 0
    with pytest.raises(TwinStoreError, match=r"E1\.usdc of epoch E1 is corrupted"):
        TwinStore.open(twin).read_epoch("E1")


def test_corrupted_crate_header_and_root_are_named(scene: CubeScene) -> None:
    twin = scene.dir / "twin"
    _flip(twin / "epochs" / "E0.usdc", 8, 8)  # the crate version
    _failed(run_gdt("show", str(twin)), "E0.usdc", "corrupted")
    # a twin without recorded sha256s (written before they were): USD's own error, with the file named
    root = twin / "twin.usda"
    text = root.read_text()
    root.write_text(text[:text.index("    customLayerData")] + text[text.index("    defaultPrim"):])
    err = _failed(run_gdt("log", str(twin)), "cannot read USD layer", "E0.usdc", "crate")
    assert "crateFile.cpp" not in err  # the gist, not the C++ location
    root.write_bytes(b"#usda 1.0\n(\n  subLayers = [ @epochs/E1.usdc@ \x00\xff")
    _failed(run_gdt("log", str(twin)), "twin.usda")


def test_a_missing_layer_is_named(scene: CubeScene) -> None:
    twin = scene.dir / "twin"
    (twin / "epochs" / "E0.usdc").unlink()
    _failed(run_gdt("show", str(twin)), "E0.usdc", "is missing", "recorded sha256")


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_damage_to_the_root_is_a_twin_store_error_or_harmless(template: CubeScene, tmp_path: Path,
                                                                  data: st.DataObject) -> None:
    twin = tmp_path / "twin"
    shutil.rmtree(twin, ignore_errors=True)
    shutil.copytree(template.dir / "twin", twin)
    root = twin / "twin.usda"
    raw = bytearray(root.read_bytes())
    for _ in range(data.draw(st.integers(1, 8))):
        raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    root.write_bytes(bytes(raw[: data.draw(st.integers(0, len(raw)))]))
    try:
        store = TwinStore.open(twin)
        for eid in store.epochs():
            store.read_epoch(eid)
    except TwinStoreError:
        pass  # named, exit 1; anything else would be exit 70


def test_a_missing_or_invalid_run_lock_is_reported(scene: CubeScene) -> None:
    twin = scene.dir / "twin"
    lock = twin / "gdt.lock"
    good = lock.read_text()
    lock.unlink()
    res = run_gdt("log", str(twin))
    assert res.returncode == 0 and "E1" in res.stdout  # the layers verify, so the twin stays readable
    assert "warning" in res.stderr and "gdt.lock is missing" in " ".join(res.stderr.split())
    lock.write_text('{"epochs": [\n  {"id": "E0",\n')
    err = " ".join(run_gdt("log", str(twin)).stderr.split())
    assert "gdt.lock is not a valid run record" in err and "line 3:1" in err
    res = run_gdt("audit", str(twin))
    assert res.returncode == 0 and "gdt.lock is not a valid run record" in " ".join(res.stderr.split())
    assert run_gdt("audit", str(twin), "--strict").returncode == 1
    lock.write_text(good.replace(TwinStore.open(twin).layer_digests()["epochs/E1.usdc"], "0" * 64))
    err = " ".join(run_gdt("log", str(twin)).stderr.split())
    assert f"records sha256 {'0' * 64} for epochs/E1.usdc" in err


def test_overwrite_refuses_a_twin_folder_with_user_files(scene: CubeScene) -> None:
    twin = scene.dir / "twin"
    (twin / "notes.txt").write_text("mine")
    (twin / "epochs" / "E1.bak").write_text("mine too")
    (twin / "epochs" / ".E2.tmp-123.usdc").write_text("")  # a killed write's temp file is the twin's own
    before = _layers(twin)
    wf = scene.dir / "workflow.yaml"
    _failed(run_gdt("run", str(wf), "--overwrite"), "refusing to overwrite", "notes.txt", "epochs/E1.bak")
    assert (twin / "notes.txt").read_text() == "mine" and _layers(twin) == before
    (twin / "notes.txt").unlink()
    (twin / "epochs" / "E1.bak").unlink()
    assert run_gdt("run", str(wf), "--overwrite", "-q").returncode == 0


def test_a_refused_writer_leaves_the_holders_lock_record(scene: CubeScene) -> None:
    twin = scene.dir / "twin"
    with holding_writer_lock(twin) as holder:
        for _ in range(2):  # the second refused writer still learns who holds the twin
            with pytest.raises(TwinStoreError, match=f"pid {holder.pid} since"), writer_lock(twin):
                pass
        assert lock_path(twin).read_text().startswith(f"pid {holder.pid} ")
        res = run_gdt("run", str(scene.dir / "workflow.yaml"), "--overwrite")
        _failed(res, f"pid {holder.pid}")
    with writer_lock(twin):
        assert lock_path(twin).read_text().startswith(f"pid {os.getpid()} ")
    assert lock_path(twin).read_text() == ""  # the holder clears its own record


def test_an_old_twin_left_by_a_killed_swap_is_put_back(scene: CubeScene) -> None:
    twin = scene.dir / "twin"
    before = _layers(twin)
    old = scene.dir / ".twin.old-999999999"
    partial = scene.dir / ".twin.partial-999999999"
    shutil.copytree(twin, partial)  # the complete new twin that was about to be renamed in
    os.rename(twin, old)
    with pytest.raises(TwinStoreError, match=r"\.twin\.old-999999999.*mv "):
        TwinStore.open(twin)
    res = run_gdt("run", str(scene.dir / "workflow.yaml"))  # the old twin is back, and holds every epoch already
    assert res.returncode == 0, res.stderr
    assert "put back the last complete twin" in " ".join(res.stderr.split()) and "up to date" in res.stdout
    assert _layers(twin) == before and TwinStore.open(twin).epochs() == ["E0", "E1"]
    assert not old.exists() and not partial.exists()  # the partial went only once the twin was back


def test_a_partial_twin_is_kept_while_no_twin_is_in_place(scene: CubeScene) -> None:
    twin = scene.dir / "twin"
    partial = scene.dir / ".twin.partial-999999999"
    os.rename(twin, partial)
    with pytest.raises(TwinStoreError, match=r"complete twin of an interrupted run .*\.twin\.partial-999999999"):
        TwinStore.open(twin)
    res = run_gdt("run", str(scene.dir / "workflow.yaml"), "-q")
    assert res.returncode == 0 and ".twin.partial-999999999" in res.stderr
    assert partial.is_dir() and TwinStore.open(twin).epochs() == ["E0", "E1"]
    half = scene.dir / ".twin.old-999999998"  # an old twin whose deletion was cut short
    shutil.copytree(partial / "epochs", half / "epochs")
    assert run_gdt("run", str(scene.dir / "workflow.yaml"), "--overwrite", "-q").returncode == 0
    assert not partial.exists() and not half.exists()


@pytest.mark.parametrize("native", [True, False])
def test_swap_replaces_the_twin_whole(scene: CubeScene, tmp_path: Path, monkeypatch, native: bool) -> None:
    twin = scene.dir / "twin"
    new = tmp_path / "new"
    shutil.copytree(twin, new)
    (new / "gdt.lock").write_text("{}")
    staging = scene.dir / ".twin.partial-1"
    os.rename(new, staging)
    if not native:
        monkeypatch.setenv("GDT_RENAME_EXCHANGE", "0")
    swap_into_place(staging, twin)
    assert (twin / "gdt.lock").read_text() == "{}" and not staging.exists()
    assert [p.name for p in scene.dir.iterdir() if p.name.startswith(".twin.")] == [".twin.lock"]
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (a / "x").touch()
    if exchange(a, b):  # Linux with renameat2 on this filesystem
        assert (b / "x").exists() and not (a / "x").exists()
    else:
        assert not native or sys.platform != "linux"
