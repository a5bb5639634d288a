"""The workflow commands: run, validate, plugins, schema."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click
from rich.console import Console
from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table

from ..errors import GdtError, WorkflowError
from .common import EXIT_ERROR, err_console, installed_registry, out_console, setup_logging
from .run_summary import run_summary


class RichProgress:
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


def rich_reporter(progress: Progress | None) -> Any:
    """A runner Reporter that prints each epoch and stage on stderr (and shows stage progress bars)."""
    from ..runner import Reporter

    class RichReporter(Reporter):
        def __init__(self) -> None:
            if progress is not None:
                self.progress = RichProgress(progress)

        def epoch_started(self, epoch: Any, index: int, total: int) -> None:
            err_console.print(f"[bold]epoch {epoch.id}[/] ({index + 1}/{total}, {epoch.role}, "
                              f"{len(epoch.inputs)} input{'s' if len(epoch.inputs) != 1 else ''})")

        def stage_finished(self, epoch: Any, index: int, spec: Any, seconds: float) -> None:
            err_console.print(f"  {spec.family:<14} {spec.name:<18} {seconds:7.2f} s")

        def executor_opened(self, name: str, executor: Any) -> None:
            dash = getattr(executor, "dashboard", None)
            err_console.print(f"tiles run on the {name} executor" + (f"; Dask dashboard: {dash}" if dash else ""),
                              highlight=False, soft_wrap=True)

        def epoch_finished(self, summary: Any) -> None:
            c = summary.counts
            err_console.print(f"  -> {summary.layer.name}: {c['unchanged']} unchanged, {c['new']} new, "
                              f"{c['removed']} removed, {c['outside_rov']} outside view, "
                              f"{c['not_comparable']} not comparable ({summary.seconds:.1f} s)")

    return RichReporter()


@click.command()
@click.argument("workflow", type=click.Path(path_type=Path))
@click.option("--twin", type=click.Path(path_type=Path), help="Write the twin here instead of the workflow's `twin:`.")
@click.option("--overwrite", is_flag=True,
              help="Rebuild an existing twin from its first epoch (replaced only once the new one is complete).")
@click.option("--from", "from_epoch", metavar="EPOCH",
              help="Keep the twin's epochs before EPOCH as they are and rebuild from EPOCH on.")
@click.option("-q", "--quiet", is_flag=True, help="No progress output.")
@click.option("-v", "--verbose", count=True, help="More log output (-v info, -vv debug).")
@click.option("--log-file", type=click.Path(path_type=Path), help="Append a structured JSON-lines log here.")
@click.option("--executor", help="Run tiles on this executor: serial, processes or dask (default: the workflow's).")
@click.option("--workers", type=click.IntRange(min=1), help="Worker processes of the executor (default: one per core).")
@click.option("--tile", type=click.FloatRange(min=0, min_open=True),
              help="Cut each epoch into 3-D tiles of this edge (twin units); see docs/scale.md.")
@click.option("--tile-elements", type=click.IntRange(min=1000),
              help="Instead of --tile: at most this many recent elements in one tile's core.")
@click.option("--address", help="Dask scheduler to use (tcp://host:8786) instead of a local cluster.")
@click.option("--report/--no-report", default=True, show_default=True,
              help="Write the HTML report of the last epoch beside the twin (<twin>_report.html; `gdt report`).")
def run(workflow: Path, twin: Path | None, overwrite: bool, from_epoch: str | None, quiet: bool, verbose: int,
        log_file: Path | None, executor: str | None, workers: int | None, tile: float | None,
        tile_elements: int | None, address: str | None, report: bool) -> None:
    """Run WORKFLOW, write its twin, and end with a summary (and the report's path). On an existing twin only the
    epochs it does not hold yet run; they are appended, and the twin's earlier epochs stay as they were."""
    from ..runner import run_workflow
    from ..workflow import load_workflow

    setup_logging(verbose, log_file)
    registry = installed_registry()
    tiling = _tiling(load_workflow(workflow, registry).model.execution, executor, workers, tile, tile_elements,
                     address)
    if overwrite and from_epoch:
        raise click.UsageError("--overwrite rebuilds every epoch, --from only the later ones: give one of them")
    kwargs = {"registry": registry, "twin": twin, "overwrite": overwrite, "from_epoch": from_epoch, "tiling": tiling}
    if quiet:
        result = run_workflow(workflow, **kwargs)
    else:
        with Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
                      console=err_console, transient=True) as progress:
            result = run_workflow(workflow, reporter=rich_reporter(progress), **kwargs)
    say_kept(result)
    if not result.epochs:
        return
    out_console.print(f"twin written to {result.twin}", highlight=False, soft_wrap=True)
    out_console.print(f"root layer: {result.twin / 'twin.usda'}   lock: {result.lock}", highlight=False,
                      soft_wrap=True)
    Console(width=max(120, out_console.width)).print(run_summary(result.twin))
    if report:
        write_run_report(result.twin)


def say_kept(result: Any) -> None:
    """Which of the twin's epochs the run kept, rebuilt or took on trust; that it is up to date, when it ran none."""
    for note in result.notes:
        err_console.print(f"note: {note}", highlight=False, soft_wrap=True)
    if result.kept:
        ran = ", ".join(s.id for s in result.epochs)
        out_console.print(f"kept {len(result.kept)} epoch{'s' if len(result.kept) != 1 else ''} of the twin as they "
                          f"were ({', '.join(result.kept)})" + (f"; ran {ran}" if ran else ""), highlight=False,
                          soft_wrap=True)
    if result.replaced:
        out_console.print(f"rebuilt from {result.replaced[0]}: the twin's {', '.join(result.replaced)} replaced",
                          highlight=False, soft_wrap=True)
    if not result.epochs:
        out_console.print(f"twin {result.twin} is up to date: it holds every epoch of the workflow (nothing ran, "
                          f"nothing was written)", highlight=False, soft_wrap=True)


def write_run_report(twin: Path) -> None:
    """The report beside the twin; a report that cannot be written is a warning: the twin is complete and kept."""
    from twin_store import TwinStoreError

    from ..report import default_output, write_report

    try:
        written = write_report(twin, default_output(twin))
    except (GdtError, TwinStoreError, OSError) as exc:
        err_console.print(f"warning: no report written: {exc}", highlight=False, soft_wrap=True)
        return
    out_console.print(f"report: {written.path} ({written.bytes / 1e6:.1f} MB, {written.points_shown:,} of "
                      f"{written.points_total:,} points shown; open it in a browser, no server needed)",
                      highlight=False, soft_wrap=True)


def _tiling(execution: Any, executor: str | None, workers: int | None, tile: float | None,
            tile_elements: int | None, address: str | None) -> Any:
    """The workflow's execution block with the command line's choices on top."""
    from ..runner import TilingOptions

    if address and not executor:
        executor = "dask"
    if tile is not None:
        tile_elements = None
    elif tile_elements is not None:
        tile = None
    else:
        tile, tile_elements = execution.tile, execution.tile_elements
    if (executor or address or workers) and tile is None and tile_elements is None:
        raise click.UsageError("an executor runs tiles: give --tile or --tile-elements (or `execution.tile` in the "
                               "workflow)")
    return TilingOptions(executor=executor or execution.executor, workers=workers or execution.workers, tile=tile,
                         max_elements=tile_elements, address=address or execution.address)


@click.command()
@click.argument("workflows", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--twin", type=click.Path(path_type=Path),
              help="Also check each workflow against this twin: which epochs a run keeps, which it runs, and any "
                   "held epoch it describes otherwise.")
def validate(workflows: tuple[Path, ...], twin: Path | None) -> None:
    """Check WORKFLOWS without running them: schema, stage names, parameters, slots, input files (and, with
    --twin, the epochs the twin already holds)."""
    from ..workflow import load_workflow

    registry = installed_registry()
    failed = 0
    for wf_path in workflows:
        try:
            held = _held(wf_path, twin, registry)
            wf = load_workflow(wf_path, registry, held=held)
            against = _against_twin(wf, twin, registry) if twin is not None else ""
        except (WorkflowError, GdtError) as exc:
            failed += 1
            for line in getattr(exc, "problems", None) or [f"{wf_path}: {exc}"]:
                click.echo(line)
            continue
        m = wf.model
        click.echo(f"{wf.path}: ok ({len(m.epochs)} epochs, {len(m.stages)} stages, twin {wf.twin_path()})"
                   + against)
    if failed:
        raise SystemExit(EXIT_ERROR)


def _held(wf_path: Path, twin: Path | None, registry: Any) -> frozenset[str]:
    """The epochs of the twin checked against whose input files may be gone."""
    from ..runner.execute import held_epochs
    from ..workflow import load_workflow

    if twin is None:
        return frozenset()
    load_workflow(wf_path, registry, check_files=False)  # the schema's problems first, without the files'
    return held_epochs(Path(twin).resolve())


def _against_twin(wf: Any, twin: Path, registry: Any) -> str:
    """What a run of the workflow would do on the twin; a GdtError naming a held epoch it describes otherwise."""
    from twin_store import TwinStore, TwinStoreError

    from ..runner import plan_from_workflow
    from ..runner.history import start_on

    if not (Path(twin) / "twin.usda").is_file():
        return f"; no twin at {twin} yet: a run makes it"
    try:
        store = TwinStore.open(twin)
        store.verify()
    except TwinStoreError as exc:
        raise GdtError(str(exc)) from exc
    start = start_on(plan_from_workflow(wf, registry), store)
    todo = [e.id for e in wf.model.epochs][len(start.kept):] if not start.extra else []
    return (f"; against {twin}: keeps {', '.join(start.kept) or 'nothing'}, runs {', '.join(todo) or 'nothing'}"
            + "".join(f"\n  note: {n}" for n in start.notes))


@click.command()
@click.option("--family", help="Only this family (reader, registrar, uncertainty, ..., executor).")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
def plugins(family: str | None, as_json: bool) -> None:
    """List the installed stages (and readers, tile executors): family, name, plugin, version."""
    registry = installed_registry()
    rows = [] if family == "executor" else registry.stages(family)
    executors = registry.executors() if family in (None, "executor") else []
    if as_json:
        click.echo(json.dumps([{"family": s.family, "name": s.name, "plugin": s.plugin,
                                "plugin_version": s.plugin_version, "version": s.version, "entry_point": s.entry_point,
                                "requires": list(s.requires), "provides": list(s.provides),
                                "tiling": getattr(s, "tiling", None), "description": s.description} for s in rows]
                               + [{"family": "executor", "name": e.name, "plugin": e.plugin,
                                   "plugin_version": e.plugin_version, "version": e.version,
                                   "entry_point": e.entry_point, "description": e.description} for e in executors],
                               indent=2))
        return
    table = Table(title=f"gdt stages ({len(rows)})")
    for col in ("family", "name", "plugin", "version", "requires -> provides"):
        table.add_column(col)
    for s in rows:
        tiles = " (in tiles)" if getattr(s, "tiling", "epoch") == "tile" else ""
        table.add_row(s.family, s.name, f"{s.plugin} {s.plugin_version} ({s.entry_point})", s.version,
                      f"{', '.join(s.requires)} -> {', '.join(s.provides)}{tiles}")
    for e in executors:
        table.add_row("executor", e.name, f"{e.plugin} {e.plugin_version} ({e.entry_point})", e.version,
                      e.description)
    Console(width=max(120, out_console.width)).print(table)


@click.command()
@click.option("-o", "--output", type=click.Path(path_type=Path), help="Write to this file instead of stdout.")
def schema(output: Path | None) -> None:
    """Print the JSON Schema of workflow files (for `# yaml-language-server: $schema=...`)."""
    from ..workflow import json_schema

    text = json.dumps(json_schema(installed_registry()), indent=2)
    if output:
        output.write_text(text + "\n", encoding="utf-8")
        err_console.print(f"schema written to {output}")
    else:
        click.echo(text)


COMMANDS = (run, validate, plugins, schema)
