"""Moving a finished twin into place with no moment where its path holds no complete twin, and recovering after a
kill: the leftovers beside a twin (``.<twin>.partial-<pid>``, ``.<twin>.old-<pid>``) are put back, removed or
reported, never silently lost."""

from __future__ import annotations

import ctypes
import errno
import os
import re
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

from .faults import fault
from .layers import fsync_path
from .names import ROOT_NAME, RUN_LOCK_NAME

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2
_UNSUPPORTED = {errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV}


def partial_path(target: Path, pid: int | None = None) -> Path:
    """Where process ``pid`` (default: this one) builds the twin before it moves it to ``target``."""
    return target.parent / f".{target.name}.partial-{os.getpid() if pid is None else pid}"


def old_path(target: Path, pid: int | None = None) -> Path:
    """Where process ``pid`` (default: this one) puts the replaced twin until it is deleted."""
    return target.parent / f".{target.name}.old-{os.getpid() if pid is None else pid}"


def exchange(a: Path, b: Path) -> bool:
    """Atomically exchange two paths (Linux renameat2 RENAME_EXCHANGE); False where the system cannot.

    Unsupported: other systems, old kernels or C libraries, and filesystems without the flag (some network and FUSE
    filesystems); ``GDT_RENAME_EXCHANGE=0`` forces the fallback, for tests. The caller then uses two renames.
    """
    if sys.platform != "linux" or os.environ.get("GDT_RENAME_EXCHANGE") == "0":
        return False
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    renameat2.restype = ctypes.c_int
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in _UNSUPPORTED:
        return False
    raise OSError(err, os.strerror(err), str(a), None, str(b))


def remove_twin(path: Path) -> None:
    """Delete a twin folder, its root first, so that a half-deleted one is never taken for a complete twin."""
    (path / ROOT_NAME).unlink(missing_ok=True)
    fault("old-half-removed")
    shutil.rmtree(path, ignore_errors=True)


def swap_into_place(staging: Path, target: Path) -> None:
    """Move the finished twin at ``staging`` to ``target``; an old twin there is replaced in one step, then deleted.

    With RENAME_EXCHANGE the target path holds the old twin, then the new one, never nothing. Without it the old
    twin is renamed aside and the new one renamed in: a kill between the two leaves no twin at the path, and the next
    run (``recover_leftovers``) puts the old one back.
    """
    fsync_path(staging)
    if not target.exists():
        os.rename(staging, target)
        fsync_path(target.parent)
        return
    old = old_path(target)
    if old.exists():
        shutil.rmtree(old)  # our own pid's: a leftover of a dead process that had it before us
    if exchange(staging, target):
        fsync_path(target.parent)
        fault("after-exchange")
        os.rename(staging, old)  # the partial path now holds the old twin
    else:
        os.rename(target, old)
        fault("between-renames")
        try:
            os.rename(staging, target)
        except BaseException:
            os.rename(old, target)
            raise
    fsync_path(target.parent)
    fault("old-renamed")
    remove_twin(old)
    fault("old-removed")


@dataclass(frozen=True)
class Leftover:
    """A folder a killed writer left beside a twin."""

    kind: str  # "partial" (being built) or "old" (being replaced)
    pid: int
    path: Path

    @property
    def complete(self) -> bool:
        """Whether it holds a whole twin (an old twin has its root; a partial one also its run record)."""
        names = (ROOT_NAME,) if self.kind == "old" else (ROOT_NAME, RUN_LOCK_NAME)
        return all((self.path / n).is_file() for n in names)


def leftovers(target: Path) -> list[Leftover]:
    """The partial and old twins beside ``target`` (of any process but this one), newest first."""
    pattern = re.compile(rf"\.{re.escape(target.name)}\.(partial|old)-(\d+)")
    found = []
    for p in target.parent.glob(f".{target.name}.*-*"):
        m = pattern.fullmatch(p.name)
        if m and p.is_dir() and int(m.group(2)) != os.getpid():
            found.append(Leftover(m.group(1), int(m.group(2)), p))
    return sorted(found, key=lambda lo: lo.path.stat().st_mtime_ns, reverse=True)


def recover_leftovers(target: Path) -> list[tuple[str, str]]:
    """Put back, remove or report what killed writers left beside ``target``; call it holding the writer lock.

    Holding the lock, every leftover belongs to a dead writer. If the target is missing, the newest complete old
    twin is put back (it is the last complete twin). Leftovers are removed only once a twin is in place; otherwise
    they are reported. Returns (action, message) pairs, action one of "restored", "removed", "kept".
    """
    found = leftovers(target)
    done: list[tuple[str, str]] = []
    if not target.exists():
        old = next((lo for lo in found if lo.kind == "old" and lo.complete), None)
        if old is not None:
            os.rename(old.path, target)
            fsync_path(target.parent)
            found.remove(old)
            done.append(("restored", f"put back the last complete twin {target} from {old.path} (a run was "
                                     f"killed while replacing it)"))
    in_place = (target / ROOT_NAME).is_file()  # a folder without a root is not a twin: keep what could restore it
    for lo in found:
        if in_place:
            if lo.kind == "old":
                remove_twin(lo.path)
            else:
                shutil.rmtree(lo.path, ignore_errors=True)
            done.append(("removed", f"removed the {lo.kind} twin of an interrupted run: {lo.path}"))
        else:
            done.append(("kept", leftover_advice(lo, target)))
    return done


def leftover_advice(lo: Leftover, target: Path) -> str:
    """What a leftover is and what to do with it, when ``target`` holds no twin."""
    if lo.kind == "old" and lo.complete:
        return (f"the last complete twin is at {lo.path} (a run was killed while replacing it): the next `gdt run` "
                f"into {target} puts it back, or move it yourself: mv {lo.path} {target}")
    if lo.complete:
        return (f"a complete twin of an interrupted run (pid {lo.pid}) is at {lo.path}: move it into place "
                f"(mv {lo.path} {target}) or delete it")
    return (f"an incomplete {lo.kind} twin of an interrupted run (pid {lo.pid}) is at {lo.path}; it was kept because "
            f"{target} holds no twin: delete it once you have what you need")
