"""``gdt add``: a new scan appended to a twin as one as-is epoch, with the stage chain the twin recorded."""

from __future__ import annotations

from pathlib import Path

import click
from rich.console import Console
from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

from .common import err_console, installed_registry, out_console, setup_logging
from .run_summary import run_summary
from .workflow_commands import rich_reporter, say_kept, write_run_report


@click.command()
@click.argument("twin", type=click.Path(path_type=Path))
@click.argument("scans", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--id", "epoch_id", help="Id of the new epoch (default: the one after the twin's last, E4 -> E5).")
@click.option("--like", metavar="EPOCH", help="Run the stage chain of this epoch (default: the twin's last as-is one).")
@click.option("--name", help="Dataset name of the scan in the twin (default: the file stem).")
@click.option("--reader", help="Reader to use (default: chosen by the file's extension).")
@click.option("--viewpoint", nargs=3, type=float, metavar="X Y Z",
              help="Where the scanner stood (twin units), for a file whose header or pose file does not say.")
@click.option("--units", help="Units of the file's coordinates (default: the twin's; E57 and CAD readers know theirs).")
@click.option("--executor", help="Run tiles on this executor: serial, processes or dask.")
@click.option("--workers", type=click.IntRange(min=1), help="Worker processes of the executor.")
@click.option("--tile", type=click.FloatRange(min=0, min_open=True),
              help="Tile edge (twin units; default: the tiles the chain's epoch ran in, if any).")
@click.option("-q", "--quiet", is_flag=True, help="No progress output.")
@click.option("-v", "--verbose", count=True, help="More log output (-v info, -vv debug).")
@click.option("--report/--no-report", default=True, show_default=True,
              help="Write the HTML report of the new epoch beside the twin.")
def add(twin: Path, scans: tuple[Path, ...], epoch_id: str | None, like: str | None, name: str | None,
        reader: str | None, viewpoint: tuple[float, float, float] | None, units: str | None,
        executor: str | None, workers: int | None, tile: float | None, quiet: bool, verbose: int,
        report: bool) -> None:
    """Append SCANS to TWIN as one new as-is epoch, run with the stage chain of the twin's last as-is epoch: each
    visit's scan needs no workflow editing. The twin's earlier epochs stay as they were."""
    from twin_store import TwinStore

    from ..audit import recorded_tiling
    from ..runner import TilingOptions, execute_plan
    from ..runner.add import plan_for_scans, template_epoch

    setup_logging(verbose, None)
    registry = installed_registry()
    store = TwinStore.open(twin)
    plan, warnings = plan_for_scans(store, registry, list(scans), epoch_id=epoch_id, like=like, name=name,
                                    reader=reader, units=units, viewpoint=viewpoint)
    for warning in warnings:
        err_console.print(f"warning: {warning}", highlight=False, soft_wrap=True)
    recorded = recorded_tiling(store, [template_epoch(store, like).epoch.id])
    size = tile or (recorded.tile if recorded else None)
    tiling = TilingOptions(executor=executor or "serial", workers=workers, tile=size) if size else None
    if tiling is None and (executor or workers):
        raise click.UsageError("an executor runs tiles: give --tile too (the chain's epoch ran in none)")
    kwargs = {"append": True, "tiling": tiling}
    if quiet:
        result = execute_plan(plan, registry, Path(twin), **kwargs)
    else:
        with Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
                      console=err_console, transient=True) as progress:
            result = execute_plan(plan, registry, Path(twin), reporter=rich_reporter(progress), **kwargs)
    say_kept(result)
    out_console.print(f"added epoch {plan.epochs[0].id} to {result.twin}", highlight=False, soft_wrap=True)
    Console(width=max(120, out_console.width)).print(run_summary(result.twin))
    if report:
        write_run_report(result.twin)


COMMANDS = (add,)
