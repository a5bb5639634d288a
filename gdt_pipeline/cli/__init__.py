"""The ``gdt`` command line: the click group, its commands and the error handling of ``main``.

Commands: workflow_commands (run, validate, plugins, schema), add_command (add), twin_commands (log, show, diff,
export, audit, calibrate), lab_commands (scene, simulate, eval). Errors end with a one-paragraph message and a
non-zero exit code (1: the input or workflow is wrong; 70: a bug in gdt or a plugin); ``--debug`` adds the traceback.
"""

from __future__ import annotations

import sys
import traceback

import click
from rich.text import Text

from twin_store import TwinStoreError

from .. import __version__
from ..errors import GdtError
from . import add_command, lab_commands, twin_commands, workflow_commands
from .common import EXIT_ERROR, EXIT_INTERNAL, err_console, out_console, setup_logging

__all__ = ["EXIT_ERROR", "EXIT_INTERNAL", "cli", "err_console", "main", "out_console", "setup_logging"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="gdt")
@click.option("--debug", is_flag=True, help="Show tracebacks on errors.")
@click.pass_context
def cli(ctx: click.Context, debug: bool) -> None:
    """gdt: build geometric digital twins from CAD and scans, epoch by epoch, with uncertainty-aware change
    detection. Each epoch is one USD layer of the twin, with per-element uncertainty, change and provenance."""
    ctx.ensure_object(dict)
    ctx.obj["debug"] = debug


for _command in (workflow_commands.COMMANDS + add_command.COMMANDS + lab_commands.COMMANDS
                 + twin_commands.COMMANDS):
    cli.add_command(_command)


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
