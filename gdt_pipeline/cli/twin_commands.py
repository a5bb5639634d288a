"""The twin commands: log, show, diff, export, audit, report (one HTML page of the twin at an epoch), and calibrate
(a sensor profile from scans of a known object)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import click
import numpy as np
from rich.console import Console
from rich.table import Table
from rich.text import Text

from twin_store import STATE_NAMES

from ..names import UNITS
from .common import EXIT_ERROR, err_console, installed_registry, out_console


def open_twin(twin: Path, epoch: str | None) -> tuple[Any, str]:
    """The twin store at ``twin`` and the epoch asked for (default: the latest), or a clear TwinStoreError."""
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


def counts_text(counts: dict[str, int]) -> str:
    """Elements per change state as one line: '3 unchanged, 1 new, 0 removed, 0 outside rov'."""
    return ", ".join(f"{counts.get(k, 0)} {k.replace('_', ' ')}" for k in STATE_NAMES)


@click.command("log")
@click.argument("twin", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@click.option("--provenance", is_flag=True, help="Print the full provenance of each epoch.")
def log_cmd(twin: Path, as_json: bool, provenance: bool) -> None:
    """List the epochs of TWIN: when, from which inputs, how many elements are unchanged/new/removed, and which
    identified parts (IFC elements by GlobalId, named CAD parts) an epoch found removed."""
    from twin_store import TwinStore

    from ..provenance import EpochProvenance
    from ..twin_elements import identified_changes, identity_label

    store = TwinStore.open(twin)
    records = store.history()  # every layer is checked against its recorded sha256 before it is read
    for problem in store.run_lock_problems():
        err_console.print(Text.assemble(("warning: ", "yellow"), problem), soft_wrap=True)
    if provenance and not as_json:
        import yaml

        for r in records:
            click.echo(f"# epoch {r.id}")
            click.echo(yaml.safe_dump(r.provenance, sort_keys=False, default_flow_style=None, width=118))
        return
    identified = identified_changes(store, [r.id for r in records])
    provs = [EpochProvenance.from_dict(r.provenance) for r in records]
    if as_json:
        click.echo(json.dumps([{"epoch": r.id, "index": r.index, "role": p.epoch.role, "started": p.started,
                                "finished": p.finished, "inputs": [dataclasses.asdict(i) for i in p.inputs],
                                "counts": r.counts, "identified_removals": identified.get(r.id, []),
                                **({"provenance": r.provenance} if provenance else {})}
                               for r, p in zip(records, provs, strict=True)], indent=2))
        return
    table = Table(title=f"{twin} ({len(records)} epochs)")
    for col in ("epoch", "role", "finished (UTC)", "inputs", "visible elements"):
        table.add_column(col)
    for r, p in zip(records, provs, strict=True):
        inputs = "\n".join(f"{i.path} ({i.sha256[:12]}, {i.elements} el.)" for i in p.inputs)
        table.add_row(r.id, p.epoch.role, p.finished, inputs, counts_text(r.counts))
    Console(width=max(140, out_console.width)).print(table)
    for r in records:
        for line in moved_lines(store, r.id):
            click.echo(line)
        for found in identified.get(r.id, []):
            share = found["removed"] / found["of"]
            what = "facets" if found["kind"] == "mesh" else "points"
            verb = "removed" if share >= 0.5 else "changed"
            click.echo(f"{r.id}: {verb}: {identity_label(found['identity'])} ({found['key']}: {found['removed']} "
                       f"of its {found['of']} {what})")


def moved_lines(store: Any, epoch_id: str) -> list[str]:
    """One line per part an epoch recorded as moved: which part, by how much, from which removed segment."""
    out = []
    for seg in store.read_segments(epoch_id, members=False):
        if seg.moved_item and seg.displacement is not None:
            d = seg.displacement
            out.append(f"{epoch_id}: {seg.moved_item} moved by {float(np.linalg.norm(d)):.4g} "
                       f"({', '.join(f'{x:.4g}' for x in d)}), turned {seg.rotation_deg:.3g}°; new segment "
                       f"{seg.id}, removed segment {seg.moved_from}")
    return out


@click.command()
@click.argument("twin", type=click.Path(path_type=Path))
@click.option("--epoch", help="Epoch id (default: the latest).")
@click.option("-o", "--output", type=click.Path(path_type=Path),
              help="Write the twin at that epoch: .usda/.usdc (flattened), .usdz, .obj, .ply (a folder of one PLY "
                   "per element set), or .png (a picture of what a USD viewer shows).")
def show(twin: Path, epoch: str | None, output: Path | None) -> None:
    """Show the twin as it was at an epoch, or write it to a file."""
    from twin_store import REASON_NAMES

    from ..export import export_twin

    store, epoch = open_twin(twin, epoch)
    if output is not None:
        for path in export_twin(store, epoch, output):
            click.echo(f"wrote {path}")
        return
    table = Table(title=f"{twin} at epoch {epoch}")
    for col in ("element set", "kind", "elements", "visible", "visible by state", "fusion reason (all elements)"):
        table.add_column(col)
    for es in store.read_epoch(epoch):
        vis = es.visible.astype(bool)
        counts = {n: int(c) for n, c in zip(STATE_NAMES, np.bincount(es.state[vis], minlength=len(STATE_NAMES)),
                                            strict=True)}
        why = "-" if es.reason is None else ", ".join(
            f"{int(c)} {REASON_NAMES[i].replace('_', ' ') if i < len(REASON_NAMES) else f'code {i}'}"
            for i, c in enumerate(np.bincount(es.reason)) if c)
        table.add_row(es.key, es.kind, str(es.n_elements), str(int(vis.sum())), counts_text(counts), why)
    Console(width=max(120, out_console.width)).print(table)


@click.command()
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


@click.command()
@click.argument("twin", type=click.Path(path_type=Path))
@click.option("--epoch", help="Epoch id (default: the latest).")
@click.option("--format", "fmt", type=click.Choice(["ply", "obj", "usdz", "usda", "usdc", "png", "las", "laz"]),
              required=True,
              help="ply: a folder with one PLY per element set (points, or mesh facets); las/laz: a folder with one "
                   "LAS 1.4 per point set; both carry change state, score, p-value, uncertainty, source epoch and "
                   "fusion reason and ratio as scalar fields (CloudCompare); obj: one file; usdz/usda/usdc: flattened "
                   "USD with the provenance of every epoch.")
@click.option("--scope", type=click.Choice(["composite", "epoch"]),
              help="For ply, las and laz: composite (the default) writes every visible element at the epoch; epoch "
                   "only the visible elements that this epoch supplied.")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="File (or folder for ply, las and laz).")
def export(twin: Path, epoch: str | None, fmt: str, scope: str | None, output: Path) -> None:
    """Export the twin at an epoch to PLY, LAS/LAZ, OBJ or USD(Z)."""

    from ..export import SCOPED_FORMATS, export_twin

    if scope is not None and fmt not in SCOPED_FORMATS:
        raise click.UsageError(f"--scope applies to --format {', '.join(SCOPED_FORMATS)} only, not {fmt}")
    store, epoch = open_twin(twin, epoch)
    for path in export_twin(store, epoch, output, fmt, scope or "composite"):
        click.echo(f"wrote {path}")


@click.command()
@click.option("--reference", type=click.Path(path_type=Path, exists=True, dir_okay=False), required=True,
              help="Mesh of the known object that was scanned.")
@click.option("--scan", "scans", type=click.Path(path_type=Path, exists=True, dir_okay=False), multiple=True,
              required=True, help="A scan of it, registered to the reference (repeat for several).")
@click.option("--units", type=click.Choice(list(UNITS)), default="m",
              show_default=True, help="Units of the files (and of the profile written).")
@click.option("--max-distance", type=float, help="Ignore points farther than this from the reference (strays).")
@click.option("--name", default="calibrated", show_default=True, help="Name of the sensor profile.")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="Profile YAML to write.")
def calibrate(reference: Path, scans: tuple[Path, ...], units: str, max_distance: float | None, name: str,
              output: Path) -> None:
    """Estimate a scanner's noise from scans of a known object and write a reusable sensor profile."""
    from ..runner import read_dataset
    from ..sensors import SensorProfile, file_digest, save_profile
    from ..sensors import calibrate as run_calibration

    registry = installed_registry()
    ref = read_dataset(reference, registry, name="reference", role="as-designed", kind="mesh")
    data = [read_dataset(p, registry, name=f"scan{i}", kind="points") for i, p in enumerate(scans)]
    cal = run_calibration(ref, data, max_distance=max_distance)
    record = {**cal.record(), "reference": {"path": str(reference), "sha256": file_digest(reference)},
              "scans": [{"path": str(p), "sha256": file_digest(p)} for p in scans],
              "method": "1.4826 * median absolute deviation of signed point-to-mesh distances (Open3D); a Student t "
                        "fitted by maximum likelihood replaces it where BIC says so (tail)"}
    sigma, dof = cal.profile_sigma, cal.dof
    noise = "Gaussian" if dof is None else f"Student t (ν {dof:.3g}, σ its scale)"
    profile = SensorProfile(name=name, units=units, range_sigma=[sigma, 0.0, 0.0], lateral_sigma=[sigma, 0.0],
                            dof=dof, calibration=record,
                            description=f"Isotropic {noise} noise calibrated against {reference.name} from "
                                        f"{len(scans)} scan(s) ({cal.n_used} points).")
    save_profile(profile, output)
    click.echo(f"sigma {cal.sigma:.6g} {units} (bias {cal.bias:+.3g}, median |d| {cal.median_abs:.3g}, p95 "
               f"{cal.p95_abs:.3g} = {cal.p95_abs / cal.sigma:.2f} sigma, {cal.n_used} of {cal.n_points} points)")
    if cal.tail is not None:
        chosen = "Student t" if cal.tail.heavy else "Gaussian"
        click.echo(f"model: {chosen}: {cal.tail.record()['why']}"
                   + (f"; t scale {cal.tail.scale:.6g} {units}" if cal.tail.heavy else ""))
    click.echo(f"profile written to {output}")


@click.command()
@click.argument("twin", type=click.Path(path_type=Path))
@click.option("--epoch", help="Re-run only this epoch, from the twin's composite before it and its own inputs "
                              "(default: every epoch from the first).")
@click.option("--strict", is_flag=True, help="A plugin version that differs from the recorded one is an error.")
@click.option("--inputs-dir", type=click.Path(path_type=Path),
              help="Folder the recorded input paths are relative to, when the data has moved.")
@click.option("--report", "report_path", type=click.Path(path_type=Path), help="Write a JSON report here.")
@click.option("--rtol", default=1e-6, show_default=True, help="Relative tolerance for floating-point values.")
@click.option("--atol", default=1e-9, show_default=True, help="Absolute tolerance for floating-point values.")
def audit(twin: Path, epoch: str | None, strict: bool, inputs_dir: Path | None, report_path: Path | None,
          rtol: float, atol: float) -> None:
    """Re-run TWIN's epochs from their recorded provenance and check they match what is stored (exit 0 only then)."""
    from ..audit import audit_twin

    report = audit_twin(twin, epoch=epoch, strict=strict, base_dir=inputs_dir, rtol=rtol, atol=atol,
                        registry=installed_registry())
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


@click.command()
@click.argument("twin", type=click.Path(path_type=Path))
@click.option("--epoch", help="Epoch id (default: the latest).")
@click.option("-o", "--output", type=click.Path(path_type=Path, dir_okay=False),
              help="HTML file to write (default: <twin folder name>_report.html beside the twin).")
@click.option("--budget", type=click.IntRange(min=0), default=500_000, show_default=True,
              help="Points drawn in the 3-D view at most (a voxel subsample of the twin's points).")
def report(twin: Path, epoch: str | None, output: Path | None, budget: int) -> None:
    """Write one self-contained HTML page of TWIN at an epoch: a 3-D view by change state, the segments, score and
    uncertainty histograms, and the provenance; it opens offline in any browser."""
    import os

    from ..report import default_output, write_report

    # read .usdc arrays with pread, not mmap: pages of a large twin's layers touched once would otherwise stay
    # resident (and counted in the RSS) until the layer closes; pread's copies are freed as soon as they are used
    os.environ.setdefault("USDC_USE_PREAD", "1")
    summary = write_report(twin, output or default_output(twin), epoch=epoch, budget=budget)
    click.echo(f"wrote {summary.path} ({summary.bytes / 1e6:.1f} MB; epoch {summary.epoch}; showing "
               f"{summary.points_shown:,} of {summary.points_total:,} points) in {summary.seconds:.1f} s")


COMMANDS = (log_cmd, show, diff, export, calibrate, audit, report)
