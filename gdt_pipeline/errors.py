"""Errors the engine reports to a user: each names the file, the stage or the key it is about."""

from __future__ import annotations


class GdtError(Exception):
    """A user-facing error: the CLI prints its message as one paragraph, without a traceback."""


class WorkflowError(GdtError):
    """A workflow file is invalid; ``problems`` lists every problem as ``file:line:col: loc: message``."""

    def __init__(self, path: str, problems: list[str]) -> None:
        self.path = path
        self.problems = problems
        count = len(problems)
        super().__init__(f"{path}: {count} problem{'s' if count != 1 else ''}:\n" + "\n".join(problems))


class InputError(GdtError):
    """An input file is missing, unreadable or holds invalid geometry."""


class StageError(GdtError):
    """A stage failed on valid input, or returned something that breaks its declared contract."""


class PluginError(GdtError):
    """A plugin is malformed (duplicate stage name, bad params model) or an unknown stage was asked for."""
