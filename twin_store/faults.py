"""Fault injection for the kill tests: named steps of a twin write where the process can be made to kill itself.

``GDT_FAULT=<step>`` (or ``<step>:<n>``, the n-th time the step is reached, counting from 1) makes the process send
itself SIGKILL at that step, so tests can prove that no kill at any step loses or half-writes the twin. It is for
tests only; when the variable is unset a step costs one dict lookup.
"""

from __future__ import annotations

import os
import signal

# Every named step, in the order a `gdt run --overwrite` reaches them.
FAULT_STEPS: tuple[str, ...] = (
    "layer-exported",    # an epoch layer is written and fsynced to its temp file, not yet renamed
    "layer-renamed",     # the epoch layer is in place; the root does not list it yet
    "root-exported",     # the new root is in its temp file
    "root-written",      # the new root (listing the epoch and its sha256) is in place
    "lock-written",      # gdt.lock is written into the partial twin
    "before-swap",       # the partial twin is complete, the target is untouched
    "between-renames",   # fallback swap only: the old twin is moved aside, the new one not yet in place
    "after-exchange",    # the new twin is at the target; the old one sits at the partial path
    "old-renamed",       # the old twin is moved to .<twin>.old-<pid>
    "old-half-removed",  # the old twin's root is deleted, its layers not yet
    "old-removed",       # the old twin is gone
)

_seen: dict[str, int] = {}


def fault(step: str) -> None:
    """Kill this process with SIGKILL if ``GDT_FAULT`` names this step (and occurrence); tests only."""
    wanted = os.environ.get("GDT_FAULT")
    if wanted is None:
        return
    name, _, nth = wanted.partition(":")
    if name != step:
        return
    _seen[step] = _seen.get(step, 0) + 1
    if _seen[step] == int(nth or 1):
        os.kill(os.getpid(), signal.SIGKILL)
