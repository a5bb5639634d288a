"""The bad-input corpus (tests/bad_inputs/cases.yaml): every case is run as a user would, with the installed `gdt`
command in a fresh folder, and must end with its expected exit code (never 70, never 0 on bad data), a message that
names the file and the place, and bounded resources (an input of at most 10 MB: under 1 GB peak RSS and 10 s).

Each case's folder is built from a base (nothing, the cube scene, or the cube scene with a twin built once per
session by `gdt run`), the corpus' small static files (tests/bad_inputs/files/), a workflow made from a template
with text edits, and named mutations (the binary files, corrupted twins) defined below. The cases run in parallel,
two `gdt` processes at a time; `pytest -s` prints a table of exit codes, seconds and peak RSS.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from .conftest import GDT, make_cube_scene, run_metered, write_cube_workflow

CORPUS = Path(__file__).resolve().parent / "bad_inputs"
FILES = CORPUS / "files"
CASES: list[dict[str, Any]] = yaml.safe_load((CORPUS / "cases.yaml").read_text(encoding="utf-8"))["cases"]
CLASSES = ("workflow", "geometry", "uncertainty", "twin", "cli")

SMALL_INPUT = 10 * 2**20  # inputs up to this size must stay within the limits below
RSS_LIMIT_MB = 1024
SECONDS_LIMIT = 10.0
# The watchdog ends a process well past the limits so that a case that regresses cannot take the machine with it.
KILL_RSS_MB = 1536
KILL_SECONDS = {True: 25.0, False: 60.0}  # by "input is small"
WORKERS = 2


# ---------------------------------------------------------------------------------------------------------------------
# Mutations: what cannot be a small static text file (binary files, corrupted twins, huge or undecodable files)


def _ply_binary_header(n_vertex: int, faces: int | None = None) -> bytes:
    head = ["ply", "format binary_little_endian 1.0", f"element vertex {n_vertex}", "property float x",
            "property float y", "property float z"]
    if faces is not None:
        head += [f"element face {faces}", "property list uchar int vertex_indices"]
    return ("\n".join([*head, "end_header"]) + "\n").encode()


def ply_binary_truncated(d: Path, name: str, declared: int, rows: int) -> None:
    """A binary PLY declaring ``declared`` vertices and holding ``rows`` of them."""
    data = np.arange(rows * 3, dtype="<f4") * 0.01
    (d / name).write_bytes(_ply_binary_header(declared) + data.tobytes())


def ply_binary_partial_row(d: Path, name: str) -> None:
    """A binary PLY of one vertex holding only 5 of its 12 bytes (Open3D fills the rest from uninitialised memory)."""
    (d / name).write_bytes(_ply_binary_header(1) + b"\x01\x02\x03\x04\x05")


def ply_binary_faces_truncated(d: Path, name: str, declared: int) -> None:
    """A binary mesh PLY with four valid vertices and a face element declaring ``declared`` faces, holding one."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype="<f4").tobytes()
    face = np.array([3], dtype="u1").tobytes() + np.array([0, 1, 2], dtype="<i4").tobytes()
    (d / name).write_bytes(_ply_binary_header(4, declared) + verts + face)


def stl_truncated(d: Path, name: str, declared: int, held: int) -> None:
    """A binary STL whose header declares ``declared`` triangles and which holds ``held`` (50 bytes each)."""
    tri = np.zeros(12, dtype="<f4")
    tri[3:12] = [0, 0, 0, 1, 0, 0, 0, 1, 0]
    body = (tri.tobytes() + b"\x00\x00") * held
    (d / name).write_bytes(b"binary stl".ljust(80, b" ") + np.uint32(declared).tobytes() + body)


def las_garbage(d: Path, name: str, size: int) -> None:
    """A ``LASF`` signature followed by seeded random bytes."""
    rng = np.random.default_rng(18)
    (d / name).write_bytes(b"LASF" + rng.integers(0, 256, size - 4, dtype=np.uint8).tobytes())


def _write_las(path: Path, n: int) -> None:
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    las = laspy.LasData(header)
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 1, (n, 3))
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.write(str(path))


def las_truncated(d: Path, name: str, n: int, keep: float) -> None:
    """A real LAS of ``n`` points written by laspy, cut to ``keep`` of its length."""
    _write_las(d / name, n)
    data = (d / name).read_bytes()
    (d / name).write_bytes(data[: int(len(data) * keep)])


def las_count_lies(d: Path, name: str, n: int, declared: int) -> None:
    """A real LAS of ``n`` points whose header (legacy point count, offset 107) claims ``declared``."""
    _write_las(d / name, n)
    data = bytearray((d / name).read_bytes())
    data[107:111] = np.uint32(declared).tobytes()
    (d / name).write_bytes(bytes(data))


def make_dir(d: Path, name: str) -> None:
    """A directory where a file is expected."""
    (d / name).mkdir(parents=True, exist_ok=True)


def non_utf8(d: Path, name: str, old: str, new_hex: str) -> None:
    """Replace text ``old`` in a file by raw bytes (hex), e.g. a Latin-1 é."""
    data = (d / name).read_bytes()
    assert old.encode() in data, f"mutation non_utf8: {old!r} not in {name}"
    (d / name).write_bytes(data.replace(old.encode(), bytes.fromhex(new_hex), 1))


def huge_workflow(d: Path, name: str, megabytes: int) -> None:
    """The base workflow followed by ``megabytes`` MB of comment lines."""
    line = "# " + "x" * 97 + "\n"
    text = (FILES / "base.yaml").read_text(encoding="utf-8") + line * (megabytes * 2**20 // len(line))
    (d / name).write_text(text, encoding="utf-8")


def deep_nesting(d: Path, name: str, depth: int) -> None:
    """A workflow whose description is a flow sequence nested ``depth`` deep."""
    base = (FILES / "base.yaml").read_text(encoding="utf-8")
    (d / name).write_text(base + "description: " + "[" * depth + "]" * depth + "\n", encoding="utf-8")


def flip_bytes(d: Path, name: str, count: int, at: float = 0.5) -> None:
    """Invert ``count`` bytes of a file starting at the fraction ``at`` of its length."""
    data = bytearray((d / name).read_bytes())
    start = int(len(data) * at)
    for i in range(start, min(start + count, len(data))):
        data[i] ^= 0xFF
    (d / name).write_bytes(bytes(data))


def truncate(d: Path, name: str, keep: float) -> None:
    """Cut a file to ``keep`` of its length."""
    data = (d / name).read_bytes()
    (d / name).write_bytes(data[: int(len(data) * keep)])


def delete(d: Path, name: str) -> None:
    """Remove a file or folder."""
    p = d / name
    shutil.rmtree(p) if p.is_dir() else p.unlink()


def replace_text(d: Path, name: str, old: str, new: str) -> None:
    """Replace text in a file (e.g. a sublayer path in the twin's root layer)."""
    text = (d / name).read_text(encoding="utf-8")
    assert old in text, f"mutation replace_text: {old!r} not in {name}"
    (d / name).write_text(text.replace(old, new), encoding="utf-8")


def move(d: Path, src: str, dst: str) -> None:
    """Rename a file or folder (e.g. the twin to the leftover name a killed swap leaves)."""
    os.replace(d / src, d / dst)


MUTATIONS: dict[str, Callable[..., None]] = {f.__name__: f for f in (
    ply_binary_truncated, ply_binary_partial_row, ply_binary_faces_truncated, stl_truncated, las_garbage,
    las_truncated, las_count_lies, make_dir, non_utf8, huge_workflow, deep_nesting, flip_bytes, truncate, delete,
    replace_text, move)}


# ---------------------------------------------------------------------------------------------------------------------
# Building a case's folder


@pytest.fixture(scope="session")
def bases(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The folders a case starts from: the cube scene, and the cube scene with its twin (built once by `gdt run`)."""
    root = tmp_path_factory.mktemp("bad_input_bases")
    scene = make_cube_scene(root / "scene", n_cube=600, n_new=150)
    write_cube_workflow(scene)
    twin = root / "twin"
    shutil.copytree(scene.dir, twin)
    proc = subprocess.run([str(GDT), "run", "workflow.yaml", "-q"], cwd=twin, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    return {"scene": scene.dir, "twin": twin}


def _workflow_text(spec: dict[str, Any], case_id: str) -> str:
    text = spec["text"] if "text" in spec else (FILES / spec["from"]).read_text(encoding="utf-8")
    for old, new in spec.get("edit", []):
        assert old in text, f"case {case_id}: edit target {old!r} is not in {spec.get('from', 'the text')}"
        text = text.replace(old, new, 1)
    return text


def prepare(case: dict[str, Any], root: Path, bases: dict[str, Path]) -> Path:
    """The case's folder, ready for its command."""
    d = root / case["id"]
    if case.get("base"):
        shutil.copytree(bases[case["base"]], d)
    else:
        d.mkdir(parents=True)
    for entry in case.get("files", []):
        src, _, dst = entry.partition(":")
        shutil.copyfile(FILES / src, d / (dst or src))
    if "workflow" in case:
        spec = case["workflow"]
        (d / spec.get("to", "wf.yaml")).write_text(_workflow_text(spec, case["id"]), encoding="utf-8")
    for name, *args in case.get("mutate", []):
        MUTATIONS[name](d, *args)
    for name, text in (case.get("write") or {}).items():
        (d / name).parent.mkdir(parents=True, exist_ok=True)
        (d / name).write_text(text, encoding="utf-8")
    return d


def tree_digest(path: Path) -> str:
    """sha256 over the relative names and bytes of every file below ``path`` (or of the file)."""
    h = hashlib.sha256()
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    for p in files:
        h.update(p.relative_to(path.parent).as_posix().encode() + b"\0" + p.read_bytes())
    return h.hexdigest()


# ---------------------------------------------------------------------------------------------------------------------
# Running a case


@dataclass
class Outcome:
    """What one case's `gdt` process did."""

    exit: int
    seconds: float
    rss_mb: float
    output: str
    input_bytes: int
    killed: str = ""
    digests_before: dict[str, str] | None = None
    digests_after: dict[str, str] | None = None
    present_after: dict[str, bool] | None = None


def run_measured(args: list[str], cwd: Path, small: bool) -> tuple[int, float, float, str, str]:
    """Run ``gdt args`` in ``cwd``: exit code, seconds, its own peak RSS (MB), output, and why it was killed."""
    env = {**os.environ, "COLUMNS": "200", "OMP_NUM_THREADS": "1"}
    out_path, err_path = cwd.parent / f"{cwd.name}.stdout", cwd.parent / f"{cwd.name}.stderr"
    with open(out_path, "wb") as out, open(err_path, "wb") as err:
        m = run_metered([str(GDT), *args], cwd=cwd, env=env, stdout=out, stderr=err,
                        kill_seconds=KILL_SECONDS[small], kill_rss_mb=KILL_RSS_MB)
    output = (out_path.read_text(errors="replace") + "\n" + err_path.read_text(errors="replace"))
    return m.returncode, m.seconds, m.peak_mb, output, m.killed


def run_case(case: dict[str, Any], root: Path, bases: dict[str, Path]) -> Outcome:
    """Prepare a case's folder, run its command and record what happened."""
    d = prepare(case, root, bases)
    size = sum(p.stat().st_size for p in d.rglob("*") if p.is_file())
    watched = case.get("unchanged", [])
    before = {p: tree_digest(d / p) for p in watched}
    code, seconds, rss, output, killed = run_measured([str(a) for a in case["cmd"]], d, size <= SMALL_INPUT)
    # The case folder's absolute path is left out, so that a pattern cannot match the temporary folder's name.
    output = output.replace(f"{d}/", "").replace(str(d), ".")
    return Outcome(code, seconds, rss, output, size, killed, before,
                   {p: tree_digest(d / p) if (d / p).exists() else "missing" for p in watched},
                   {p: (d / p).exists() for p in [*case.get("absent", []), *case.get("present", [])]})


@pytest.fixture(scope="session")
def outcomes(request: pytest.FixtureRequest, bases: dict[str, Path],
             tmp_path_factory: pytest.TempPathFactory) -> dict[str, Outcome]:
    """Every selected case, run two at a time; the summary table is printed (visible with -s)."""
    wanted = {item.callspec.params["case"]["id"] for item in request.session.items
              if item.originalname == "test_bad_input" and hasattr(item, "callspec")}
    root = tmp_path_factory.mktemp("bad_inputs")
    todo = [c for c in CASES if c["id"] in wanted]
    with ThreadPoolExecutor(WORKERS) as pool:
        results = dict(zip([c["id"] for c in todo], pool.map(lambda c: run_case(c, root, bases), todo), strict=True))
    print(f"\n{'case':<34} {'class':<11} {'exit':>4} {'want':>4} {'s':>6} {'MB':>6}  first line")
    for c in todo:
        r = results[c["id"]]
        first = next((ln for ln in r.output.splitlines() if ln.strip()), "")[:110]
        print(f"{c['id']:<34} {c['class']:<11} {r.exit:>4} {c['exit']:>4} {r.seconds:6.1f} {r.rss_mb:6.0f}  "
              f"{r.killed or first}")
    return results


# ---------------------------------------------------------------------------------------------------------------------
# The tests


def test_corpus_is_complete() -> None:
    """At least 80 cases, about 20 per class, each saying why it is bad and what must be said about it."""
    ids = [c["id"] for c in CASES]
    assert len(ids) >= 80 and len(set(ids)) == len(ids)
    per_class = {k: sum(c["class"] == k for c in CASES) for k in CLASSES}
    assert set(c["class"] for c in CASES) <= set(CLASSES)
    assert all(per_class[k] >= 18 for k in CLASSES if k != "cli"), per_class
    for c in CASES:
        assert c.get("why") and c.get("match") and c.get("cmd"), c["id"]
        assert c["exit"] in (1, 2) or (c["exit"] == 0 and c.get("report_only")), c["id"]
        assert set(c) <= {"id", "class", "why", "base", "files", "workflow", "write", "mutate", "cmd", "exit",
                          "match", "report_only", "unchanged", "absent", "present"}, c["id"]
        for name, *_ in c.get("mutate", []):
            assert name in MUTATIONS, f"{c['id']}: unknown mutation {name}"


@pytest.mark.parametrize("case", CASES, ids=[c["id"] for c in CASES])
def test_bad_input(case: dict[str, Any], outcomes: dict[str, Outcome]) -> None:
    """The case ends as the corpus says: exit code, a message naming the file and the place, bounded resources."""
    r = outcomes[case["id"]]
    head = f"{case['id']} ({case['why']}): exit {r.exit}, {r.seconds:.1f} s, {r.rss_mb:.0f} MB\n{r.output[-3000:]}"
    assert not r.killed, f"{r.killed}; {head}"
    assert r.exit != 70, f"internal error on bad input: {head}"
    assert r.exit == case["exit"], head
    patterns = case["match"] if isinstance(case["match"], list) else [case["match"]]
    for pattern in patterns:
        assert re.search(pattern, r.output, re.S), f"message does not match {pattern!r}: {head}"
    if r.input_bytes <= SMALL_INPUT:
        assert r.seconds < SECONDS_LIMIT, f"too slow: {head}"
        assert r.rss_mb < RSS_LIMIT_MB, f"too much memory: {head}"
    for path in case.get("unchanged", []):
        assert r.digests_after[path] == r.digests_before[path], f"{path} changed: {head}"
    for path in case.get("absent", []):
        assert not r.present_after[path], f"{path} exists after a refused command: {head}"
    for path in case.get("present", []):
        assert r.present_after[path], f"{path} is gone: {head}"
