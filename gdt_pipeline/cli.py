"""The ``gdt`` command line: run, validate, plugins, schema, scene.

Errors end with a one-paragraph message and a non-zero exit code (1: the input or workflow is wrong; 70: a bug in
gdt or a plugin); ``--debug`` adds the traceback.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sys
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click
import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

from twin_store import TwinStoreError

from . import __version__
from .errors import GdtError, WorkflowError

err_console = Console(stderr=True)
out_console = Console()
EXIT_ERROR = 1
EXIT_INTERNAL = 70


class JsonLinesHandler(logging.Handler):
    """Structured log: one JSON object per record, with the ``event`` fields the runner attaches."""

    def __init__(self, path: Path) -> None:
        super().__init__()
        self._fh = open(path, "a", encoding="utf-8")  # noqa: SIM115  (closed in close())

    def emit(self, record: logging.LogRecord) -> None:
        """Write one record."""
        data: dict[str, Any] = {"time": record.created, "level": record.levelname, "logger": record.name,
                                "message": record.getMessage()}
        data.update(getattr(record, "event", {}) or {})
        self._fh.write(json.dumps(data, default=str) + "\n")
        self._fh.flush()

    def close(self) -> None:
        """Close the file."""
        self._fh.close()
        super().close()


def _setup_logging(verbose: int, log_file: Path | None) -> None:
    from rich.logging import RichHandler

    root = logging.getLogger("gdt")
    root.handlers.clear()
    root.setLevel(logging.DEBUG)
    console = RichHandler(console=err_console, show_path=False, show_time=False)
    console.setLevel(logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG)
    root.addHandler(console)
    if log_file is not None:
        handler = JsonLinesHandler(log_file)
        handler.setLevel(logging.DEBUG)
        root.addHandler(handler)
    root.propagate = False


class _RichProgress:
    """Progress tasks of stages shown as rich progress bars."""

    def __init__(self, progress: Progress) -> None:
        self._p = progress

    @contextlib.contextmanager
    def task(self, description: str, total: float) -> Iterator[Any]:
        """A bar for the duration of the block."""
        tid = self._p.add_task(description, total=total)
        try:
            yield lambda advance=1.0: self._p.advance(tid, advance)
        finally:
            self._p.remove_task(tid)


def _reporter(progress: Progress | None) -> Any:
    from .runner import Reporter

    class RichReporter(Reporter):
        def __init__(self) -> None:
            if progress is not None:
                self.progress = _RichProgress(progress)

        def epoch_started(self, epoch: Any, index: int, total: int) -> None:
            err_console.print(f"[bold]epoch {epoch.id}[/] ({index + 1}/{total}, {epoch.role}, "
                              f"{len(epoch.inputs)} input{'s' if len(epoch.inputs) != 1 else ''})")

        def stage_finished(self, epoch: Any, index: int, spec: Any, seconds: float) -> None:
            err_console.print(f"  {spec.family:<14} {spec.name:<18} {seconds:7.2f} s")

        def epoch_finished(self, summary: Any) -> None:
            c = summary.counts
            err_console.print(f"  -> {summary.layer.name}: {c['unchanged']} unchanged, {c['new']} new, "
                              f"{c['removed']} removed, {c['outside_rov']} outside view ({summary.seconds:.1f} s)")

    return RichReporter()


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="gdt")
@click.option("--debug", is_flag=True, help="Show tracebacks on errors.")
@click.pass_context
def cli(ctx: click.Context, debug: bool) -> None:
    """gdt: build geometric digital twins from CAD and scans, epoch by epoch, with uncertainty-aware change
    detection. Each epoch is one USD layer of the twin, with per-element uncertainty, change and provenance."""
    ctx.ensure_object(dict)
    ctx.obj["debug"] = debug


def _registry() -> Any:
    from .plugins import load_registry

    reg = load_registry()
    for w in reg.warnings:
        err_console.print(Text.assemble(("warning: ", "yellow"), w))
    return reg


@cli.command()
@click.argument("workflow", type=click.Path(path_type=Path))
@click.option("--twin", type=click.Path(path_type=Path), help="Write the twin here instead of the workflow's `twin:`.")
@click.option("--overwrite", is_flag=True, help="Replace an existing twin (only once the new one is complete).")
@click.option("-q", "--quiet", is_flag=True, help="No progress output.")
@click.option("-v", "--verbose", count=True, help="More log output (-v info, -vv debug).")
@click.option("--log-file", type=click.Path(path_type=Path), help="Append a structured JSON-lines log here.")
def run(workflow: Path, twin: Path | None, overwrite: bool, quiet: bool, verbose: int, log_file: Path | None) -> None:
    """Run WORKFLOW end to end and write its twin."""
    from .runner import run_workflow

    _setup_logging(verbose, log_file)
    registry = _registry()
    if quiet:
        result = run_workflow(workflow, registry=registry, twin=twin, overwrite=overwrite)
    else:
        with Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
                      console=err_console, transient=True) as progress:
            result = run_workflow(workflow, registry=registry, twin=twin, overwrite=overwrite,
                                  reporter=_reporter(progress))
    out_console.print(f"twin written to {result.twin}", highlight=False, soft_wrap=True)
    out_console.print(f"root layer: {result.twin / 'twin.usda'}   lock: {result.lock}", highlight=False,
                      soft_wrap=True)


@cli.command()
@click.argument("workflows", nargs=-1, required=True, type=click.Path(path_type=Path))
def validate(workflows: tuple[Path, ...]) -> None:
    """Check WORKFLOWS without running them: schema, stage names, parameters, slots, input files."""
    from .workflow import load_workflow

    registry = _registry()
    failed = 0
    for wf_path in workflows:
        try:
            wf = load_workflow(wf_path, registry)
        except WorkflowError as exc:
            failed += 1
            for line in exc.problems:
                click.echo(line)
            continue
        m = wf.model
        click.echo(f"{wf.path}: ok ({len(m.epochs)} epochs, {len(m.stages)} stages, twin {wf.twin_path()})")
    if failed:
        raise SystemExit(EXIT_ERROR)


@cli.command()
@click.option("--family", help="Only this family (reader, registrar, uncertainty, ...).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
def plugins(family: str | None, as_json: bool) -> None:
    """List the installed stages: family, name, plugin, version."""
    registry = _registry()
    rows = registry.stages(family)
    if as_json:
        click.echo(json.dumps([{"family": s.family, "name": s.name, "plugin": s.plugin,
                                "plugin_version": s.plugin_version, "version": s.version, "entry_point": s.entry_point,
                                "requires": list(s.requires), "provides": list(s.provides),
                                "description": s.description} for s in rows], indent=2))
        return
    table = Table(title=f"gdt stages ({len(rows)})")
    for col in ("family", "name", "plugin", "version", "requires -> provides"):
        table.add_column(col)
    for s in rows:
        table.add_row(s.family, s.name, f"{s.plugin} {s.plugin_version} ({s.entry_point})", s.version,
                      f"{', '.join(s.requires)} -> {', '.join(s.provides)}")
    Console(width=max(120, out_console.width)).print(table)


@cli.command()
@click.option("-o", "--output", type=click.Path(path_type=Path), help="Write to this file instead of stdout.")
def schema(output: Path | None) -> None:
    """Print the JSON Schema of workflow files (for `# yaml-language-server: $schema=...`)."""
    from .workflow import json_schema

    text = json.dumps(json_schema(_registry()), indent=2)
    if output:
        output.write_text(text + "\n", encoding="utf-8")
        err_console.print(f"schema written to {output}")
    else:
        click.echo(text)


SCENES = {"test-scene": "the demo (CAD and one noisy ToF epoch; workflows/demo.yaml)",
          "paper-test-scene": "the paper's four epochs (workflows/test_scene.yaml)",
          "fuselage": "the paper's fuselage section, five brackets added and one removed (workflows/fuselage.yaml)"}


def make_scene(name: str, out_dir: Path, seed: int) -> None:
    """Generate one of the bundled synthetic scenes."""
    if name == "test-scene":
        from .scenes import make_test_scene

        make_test_scene(out_dir, seed=seed)
    elif name == "paper-test-scene":
        from .paper_scenes import make_paper_test_scene

        make_paper_test_scene(out_dir, seed=seed)
    else:
        from .fuselage_scene import make_fuselage_scene

        make_fuselage_scene(out_dir, seed=seed)


@cli.command()
@click.argument("name", type=click.Choice(list(SCENES)))
@click.argument("out_dir", type=click.Path(path_type=Path))
@click.option("--seed", default=0, show_default=True, help="Seed of the simulated scans.")
def scene(name: str, out_dir: Path, seed: int) -> None:
    """Generate a synthetic scene (CAD, simulated scans, ground truth) into OUT_DIR.

    test-scene: the demo; paper-test-scene: the paper's four epochs; fuselage: the paper's fuselage section."""
    make_scene(name, out_dir, seed)
    click.echo(f"scene {name!r} written to {out_dir}")


def _floats(text: str, n: int, what: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != n:
        raise click.BadParameter(f"{what} must be {n} comma-separated numbers, got {text!r}")
    return vals


@cli.command()
@click.argument("meshes", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--station", "stations", multiple=True, required=True, metavar="X,Y,Z",
              help="Scanner position (repeat for several scans).")
@click.option("--target", required=True, metavar="X,Y,Z", help="Where the scanners look.")
@click.option("--profile", default="tof_low_cost", show_default=True,
              help="Noise: tof_low_cost, structured_light or a sensor profile YAML.")
@click.option("--kind", type=click.Choice(["pinhole", "spherical"]), default="pinhole", show_default=True)
@click.option("--fov", "fov_deg", default=60.0, show_default=True, help="Field of view (deg).")
@click.option("--density", "points_per_m2", default=20000.0, show_default=True, help="Points per m² at the target.")
@click.option("--max-range", default=10.0, show_default=True, help="Farthest hit kept (m).")
@click.option("--registration-sigma-deg", default=0.0, show_default=True, help="Per-scan rotation error (deg).")
@click.option("--registration-sigma-m", default=0.0, show_default=True, help="Per-scan translation error (m).")
@click.option("--mesh", "as_mesh", is_flag=True, help="Write reconstructed surfaces (Poisson) instead of points.")
@click.option("--seed", default=0, show_default=True)
@click.option("-o", "--out", "out", required=True, type=click.Path(path_type=Path),
              help="Output PLY; with several stations, _s0, _s1 ... are appended.")
def simulate(meshes: tuple[Path, ...], stations: tuple[str, ...], target: str, profile: str, kind: str,
             fov_deg: float, points_per_m2: float, max_range: float, registration_sigma_deg: float,
             registration_sigma_m: float, as_mesh: bool, seed: int, out: Path) -> None:
    """Simulate scans of MESHES (any format trimesh reads) by ray casting, with the sensor's noise.

    Beside each scan go its pose and scanner (<scan>_pose.json) and per-point truth (<scan>_truth.npz: noise-free
    position, object and facet hit, sigmas)."""
    import numpy as np
    import trimesh

    from .sensors import load_profile
    from .simulate import ScannerSpec, simulate_scan, write_scan

    loaded = []
    for path in meshes:
        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as exc:
            raise click.ClickException(f"{path}: cannot read a mesh: {exc}") from exc
        if not len(getattr(mesh, "faces", [])):
            raise click.ClickException(f"{path}: no triangles to scan")
        loaded.append(mesh)
    try:
        sensor = load_profile(profile, Path.cwd())
    except Exception as exc:
        raise click.ClickException(f"--profile {profile!r}: {exc}") from exc
    spec = ScannerSpec(kind=kind, fov_deg=fov_deg, points_per_m2=points_per_m2, max_range=max_range,
                       profile=sensor.name, registration_sigma_deg=registration_sigma_deg,
                       registration_sigma_m=registration_sigma_m)
    rng = np.random.default_rng(seed)
    aim = np.array(_floats(target, 3, "--target"))
    names = [p.stem for p in meshes]
    for k, text in enumerate(stations):
        eye = np.array(_floats(text, 3, "--station"))
        scan = simulate_scan(loaded, eye, aim, spec, rng, profile=sensor)
        path = out if len(stations) == 1 else out.with_name(f"{out.stem}_s{k}{out.suffix or '.ply'}")
        written = write_scan(scan, path, object_names=names, spec=spec, as_mesh=as_mesh)
        click.echo(f"{written['scan']}: {len(scan.points)} points from {text} (truth: {written['truth'].name})")


@cli.command("eval")
@click.argument("workflow", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--twin", type=click.Path(path_type=Path), help="Evaluate this existing twin instead of running.")
@click.option("--json", "json_path", type=click.Path(path_type=Path), help="Write the results as JSON here.")
@click.option("--report", "report_dir", type=click.Path(path_type=Path),
              help="Markdown report with plots (default: out/eval/<workflow name>/).")
@click.option("--peers", default="c2c,m3c2,m3c2ep", show_default=True,
              help="Peers to run side by side (comma list of c2c, m3c2, m3c2ep; 'none' for none).")
@click.option("--generate/--no-generate", default=True, show_default=True,
              help="Generate a bundled scene (seed 0) when the workflow's data is missing.")
@click.option("--fusion", type=click.Choice(["most_reliable", "keep_unchanged", "keep_reference", "replace_in_view"]),
              help="Run with this fusion policy instead of the workflow's (twin: <twin>_<fusion>), to compare "
                   "the composites.")
def eval_cmd(workflow: Path, twin: Path | None, json_path: Path | None, report_dir: Path | None, peers: str,
             generate: bool, fusion: str | None) -> None:
    """Run WORKFLOW on a simulated scene and score every epoch against the scene's ground truth, with the peers."""
    from .evaluate import PEERS, evaluate, format_table, missing_scene, with_fusion

    chosen = () if peers.strip() == "none" else tuple(p.strip() for p in peers.split(",") if p.strip())
    unknown = [p for p in chosen if p not in PEERS]
    if unknown:
        raise click.BadParameter(f"unknown peers {unknown}; choose from {', '.join(PEERS)}", param_hint="--peers")
    registry = _registry()
    need = missing_scene(workflow, registry)
    if need is not None:
        name, out_dir = need
        if name is None or not generate:
            raise click.ClickException(f"{workflow}: its input data is missing in {out_dir}" +
                                       ("" if name is None else f"; generate it: gdt scene {name} {out_dir}"))
        err_console.print(f"generating the {name} scene into {out_dir} (seed 0) ...")
        make_scene(name, out_dir, 0)
    variant = with_fusion(workflow, fusion) if fusion else None
    try:
        result, arrays = evaluate(variant or workflow, twin=twin, registry=registry, peers=chosen,
                                  progress=lambda m: err_console.print(m))
    finally:
        if variant is not None:
            variant.unlink(missing_ok=True)
    if fusion:
        result["fusion_override"] = fusion
    click.echo(format_table(result))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(result, indent=2, default=float) + "\n", encoding="utf-8")
        click.echo(f"results written to {json_path}")
    from .report import write_report

    out = report_dir or Path("out") / "eval" / (workflow.stem + (f"_{fusion}" if fusion else ""))
    click.echo(f"report: {write_report(result, arrays, out)}")


def _open_twin(twin: Path, epoch: str | None) -> tuple[Any, str]:
    from twin_store import TwinStore, TwinStoreError

    store = TwinStore.open(twin)
    epochs = store.epochs()
    if not epochs:
        raise TwinStoreError(f"twin {twin} has no epochs yet")
    if epoch is None:
        return store, epochs[-1]
    if epoch not in epochs:
        raise TwinStoreError(f"twin {twin} has no epoch {epoch!r} (epochs: {', '.join(epochs)})")
    return store, epoch


def _counts_text(counts: dict[str, int]) -> str:
    return ", ".join(f"{counts.get(k, 0)} {k.replace('_', ' ')}" for k in ("unchanged", "new", "removed",
                                                                             "outside_rov"))


@cli.command("log")
@click.argument("twin", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@click.option("--provenance", is_flag=True, help="Print the full provenance of each epoch.")
def log_cmd(twin: Path, as_json: bool, provenance: bool) -> None:
    """List the epochs of TWIN: when, from which inputs, and how many elements are unchanged/new/removed."""
    from twin_store import TwinStore

    records = TwinStore.open(twin).history()
    if provenance and not as_json:
        import yaml

        for r in records:
            click.echo(f"# epoch {r.id}")
            click.echo(yaml.safe_dump(r.provenance, sort_keys=False, default_flow_style=None, width=118))
        return
    if as_json:
        click.echo(json.dumps([{"epoch": r.id, "index": r.index, "role": r.role, "started": r.started,
                                "finished": r.finished, "inputs": r.inputs, "counts": r.counts,
                                **({"provenance": r.provenance} if provenance else {})} for r in records], indent=2))
        return
    table = Table(title=f"{twin} ({len(records)} epochs)")
    for col in ("epoch", "role", "finished (UTC)", "inputs", "visible elements"):
        table.add_column(col)
    for r in records:
        inputs = "\n".join(f"{i.get('path')} ({str(i.get('sha256', ''))[:12]}, {i.get('elements', '?')} el.)"
                           for i in r.inputs)
        table.add_row(r.id, r.role, r.finished, inputs, _counts_text(r.counts))
    Console(width=max(140, out_console.width)).print(table)


@cli.command()
@click.argument("twin", type=click.Path(path_type=Path))
@click.option("--epoch", help="Epoch id (default: the latest).")
@click.option("-o", "--output", type=click.Path(path_type=Path),
              help="Write the twin at that epoch: .usda/.usdc (flattened), .usdz, .obj, .ply (a folder of one PLY "
                   "per element set), or .png (a picture of what a USD viewer shows).")
def show(twin: Path, epoch: str | None, output: Path | None) -> None:
    """Show the twin as it was at an epoch, or write it to a file."""
    from twin_store import REASON_NAMES

    from .export import export_twin

    store, epoch = _open_twin(twin, epoch)
    if output is not None:
        for path in export_twin(store, epoch, output):
            click.echo(f"wrote {path}")
        return
    table = Table(title=f"{twin} at epoch {epoch}")
    for col in ("element set", "kind", "elements", "visible", "visible by state", "fusion reason (all elements)"):
        table.add_column(col)
    for es in store.read_epoch(epoch):
        vis = es.visible.astype(bool)
        counts = {n: int(c) for n, c in zip(("unchanged", "new", "removed", "outside_rov"),
                                            np.bincount(es.state[vis], minlength=4), strict=True)}
        why = "-" if es.reason is None else ", ".join(
            f"{int(c)} {REASON_NAMES[i].replace('_', ' ') if i < len(REASON_NAMES) else f'code {i}'}"
            for i, c in enumerate(np.bincount(es.reason)) if c)
        table.add_row(es.key, es.kind, str(es.n_elements), str(int(vis.sum())), _counts_text(counts), why)
    Console(width=max(120, out_console.width)).print(table)


@cli.command()
@click.argument("twin", type=click.Path(path_type=Path))
@click.argument("epoch_a")
@click.argument("epoch_b")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
def diff(twin: Path, epoch_a: str, epoch_b: str, as_json: bool) -> None:
    """What changed in TWIN from EPOCH_A to EPOCH_B, per element set."""
    from twin_store import TwinStore

    rows = TwinStore.open(twin).diff(epoch_a, epoch_b)
    if as_json:
        click.echo(json.dumps([r.__dict__ for r in rows], indent=2))
        return
    table = Table(title=f"{twin}: {epoch_a} -> {epoch_b}")
    for col in ("element set", "kind", "status", "came in", "went out", "state changes"):
        table.add_column(col)
    for r in rows:
        changes = ", ".join(f"{k}: {v}" for k, v in r.transitions.items()) or "-"
        table.add_row(r.key, r.kind, "added" if r.added else "kept", str(r.came_in), str(r.went_out), changes)
    Console(width=max(120, out_console.width)).print(table)


@cli.command()
@click.argument("twin", type=click.Path(path_type=Path))
@click.option("--epoch", help="Epoch id (default: the latest).")
@click.option("--format", "fmt", type=click.Choice(["ply", "obj", "usdz", "usda", "usdc", "png"]), required=True,
              help="ply: a folder with one PLY per element set; obj: one file; usdz/usda/usdc: flattened USD with "
                   "the provenance of every epoch.")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="File (or folder for ply).")
def export(twin: Path, epoch: str | None, fmt: str, output: Path) -> None:
    """Export the twin at an epoch to PLY, OBJ or USD(Z)."""

    from .export import export_twin

    store, epoch = _open_twin(twin, epoch)
    for path in export_twin(store, epoch, output, fmt):
        click.echo(f"wrote {path}")


@cli.command()
@click.option("--reference", type=click.Path(path_type=Path, exists=True, dir_okay=False), required=True,
              help="Mesh of the known object that was scanned.")
@click.option("--scan", "scans", type=click.Path(path_type=Path, exists=True, dir_okay=False), multiple=True,
              required=True, help="A scan of it, registered to the reference (repeat for several).")
@click.option("--units", type=click.Choice(["m", "dm", "cm", "mm", "um", "in", "ft"]), default="m",
              show_default=True, help="Units of the files (and of the profile written).")
@click.option("--max-distance", type=float, help="Ignore points farther than this from the reference (strays).")
@click.option("--name", default="calibrated", show_default=True, help="Name of the sensor profile.")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="Profile YAML to write.")
def calibrate(reference: Path, scans: tuple[Path, ...], units: str, max_distance: float | None, name: str,
              output: Path) -> None:
    """Estimate a scanner's noise from scans of a known object and write a reusable sensor profile."""
    from .runner import read_dataset
    from .sensors import SensorProfile, file_digest, save_profile
    from .sensors import calibrate as run_calibration

    registry = _registry()
    ref = read_dataset(reference, registry, name="reference", role="as-designed", kind="mesh")
    data = [read_dataset(p, registry, name=f"scan{i}", kind="points") for i, p in enumerate(scans)]
    cal = run_calibration(ref, data, max_distance=max_distance)
    record = {**cal.record(), "reference": {"path": str(reference), "sha256": file_digest(reference)},
              "scans": [{"path": str(p), "sha256": file_digest(p)} for p in scans],
              "method": "1.4826 * median absolute deviation of signed point-to-mesh distances (Open3D)"}
    profile = SensorProfile(name=name, units=units, range_sigma=[cal.sigma, 0.0, 0.0], lateral_sigma=[cal.sigma, 0.0],
                            description=f"Isotropic noise calibrated against {reference.name} from {len(scans)} "
                                        f"scan(s) ({cal.n_used} points).", calibration=record)
    save_profile(profile, output)
    click.echo(f"sigma {cal.sigma:.6g} {units} (bias {cal.bias:+.3g}, median |d| {cal.median_abs:.3g}, p95 "
               f"{cal.p95_abs:.3g}, {cal.n_used} of {cal.n_points} points); profile written to {output}")


@cli.command()
@click.argument("twin", type=click.Path(path_type=Path))
@click.option("--epoch", help="Audit the epochs up to this one (default: all).")
@click.option("--strict", is_flag=True, help="A plugin version that differs from the recorded one is an error.")
@click.option("--inputs-dir", type=click.Path(path_type=Path),
              help="Folder the recorded input paths are relative to, when the data has moved.")
@click.option("--report", "report_path", type=click.Path(path_type=Path), help="Write a JSON report here.")
@click.option("--rtol", default=1e-6, show_default=True, help="Relative tolerance for floating-point values.")
@click.option("--atol", default=1e-9, show_default=True, help="Absolute tolerance for floating-point values.")
def audit(twin: Path, epoch: str | None, strict: bool, inputs_dir: Path | None, report_path: Path | None,
          rtol: float, atol: float) -> None:
    """Re-run TWIN's epochs from their recorded provenance and check they match what is stored (exit 0 only then)."""
    from .audit import audit_twin

    report = audit_twin(twin, epoch=epoch, strict=strict, base_dir=inputs_dir, rtol=rtol, atol=atol,
                        registry=_registry())
    for w in report.warnings:
        err_console.print(Text.assemble(("error: " if strict else "warning: ", "red" if strict else "yellow"), w))
    for e in report.epochs:
        if e.verdict == "match":
            how = "bit-identical" if e.exact else f"within rtol {rtol:g}, atol {atol:g}"
            keys = "" if e.cache_keys_match else "; cache keys differ (plugin versions changed)"
            click.echo(f"{e.epoch}: match ({how}{keys})")
        else:
            click.echo(f"{e.epoch}: {e.verdict.upper()}")
            for line in e.input_problems:
                click.echo(f"    {line}")
            for d in e.differences[:10]:
                click.echo(f"    {d.text()}")
            if len(e.differences) > 10:
                click.echo(f"    ... and {len(e.differences) - 10} more")
    if report_path is not None:
        report_path.parent.mkdir(parents=True, exist_ok=True)
        report_path.write_text(json.dumps(report.to_dict(), indent=2, default=str) + "\n", encoding="utf-8")
        click.echo(f"report written to {report_path}")
    click.echo("audit passed" if report.ok else "audit FAILED")
    if not report.ok:
        raise SystemExit(EXIT_ERROR)


def main() -> None:
    """Entry point of the ``gdt`` command."""
    debug = "--debug" in sys.argv[1:]
    try:
        cli.main(standalone_mode=False)
    except click.exceptions.Exit as exc:
        raise SystemExit(exc.exit_code) from None
    except click.ClickException as exc:
        exc.show()
        raise SystemExit(exc.exit_code) from None
    except click.exceptions.Abort:
        err_console.print("aborted")
        raise SystemExit(130) from None
    except KeyboardInterrupt:
        err_console.print("interrupted; nothing was written to the twin")
        raise SystemExit(130) from None
    except (GdtError, TwinStoreError) as exc:
        if debug:
            traceback.print_exc()
        err_console.print(Text.assemble(("error: ", "bold red"), str(exc)), soft_wrap=True)
        raise SystemExit(EXIT_ERROR) from None
    except SystemExit:
        raise
    except Exception as exc:
        if debug:
            traceback.print_exc()
        err_console.print(Text.assemble(("internal error: ", "bold red"), f"{type(exc).__name__}: {exc}\n"
                                        "This is a bug in gdt or in a plugin; rerun with --debug for the traceback "
                                        "and report it."), soft_wrap=True)
        raise SystemExit(EXIT_INTERNAL) from None


if __name__ == "__main__":
    main()
