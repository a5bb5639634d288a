"""What the command modules share: the consoles, the exit codes, the installed registry and the log set-up."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import click
from rich.console import Console
from rich.text import Text

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


def setup_logging(verbose: int, log_file: Path | None) -> None:
    """Send the ``gdt`` loggers to the terminal (warnings; -v info, -vv debug) and, all of it, to ``log_file``."""
    from rich.logging import RichHandler

    root = logging.getLogger("gdt")
    root.handlers.clear()
    root.setLevel(logging.DEBUG)
    console = RichHandler(console=err_console, show_path=False, show_time=False)
    console.setLevel(logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG)
    root.addHandler(console)
    if log_file is not None:
        try:
            handler = JsonLinesHandler(log_file)
        except OSError as exc:  # a usage error, not a crash: name the file and why
            raise click.BadParameter(f"{log_file}: cannot append to it ({exc.strerror})",
                                     param_hint="'--log-file'") from exc
        handler.setLevel(logging.DEBUG)
        root.addHandler(handler)
    root.propagate = False


def installed_registry() -> Any:
    """The registry of installed stages, its warnings (broken or blocked plugins) printed on stderr."""
    from ..plugins import load_registry

    reg = load_registry()
    for w in reg.warnings:
        err_console.print(Text.assemble(("warning: ", "yellow"), w))
    return reg
