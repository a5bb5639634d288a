"""Run a command and write its exit code, wall time and peak RSS as JSON to a file; kill it past a time or memory
limit. Used by the tests that bound time and memory (the bad-input corpus, bounded searches).

Why a process of its own: Linux carries a process's peak RSS across ``exec`` into ``ru_maxrss``, so a child forked
from the pytest process (gigabytes after the heavier tests) reports pytest's peak, not its own. Forked from this
small interpreter, the command's ``ru_maxrss`` (read with ``os.wait4``) is its own.

Usage: python child_meter.py RESULT.json KILL_SECONDS KILL_RSS_MB COMMAND [ARGS...]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time


def _rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def main() -> None:
    """Run the command, watch it, and write the result file."""
    result, kill_seconds, kill_mb, cmd = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), sys.argv[4:]
    killed = ""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL)  # stdout, stderr, cwd and env are this process's
    while True:
        # Reap with WNOHANG here, so the pid polled for its RSS is never a reused one.
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        elapsed = time.perf_counter() - t0
        if not killed and elapsed > kill_seconds:
            killed = f"killed after {elapsed:.0f} s"
            proc.kill()
        elif not killed and _rss_mb(proc.pid) > kill_mb:
            killed = f"killed above {kill_mb:.0f} MB RSS"
            proc.kill()
        time.sleep(0.02)
    with open(result, "w", encoding="utf-8") as fh:
        json.dump({"returncode": os.waitstatus_to_exitcode(status), "seconds": time.perf_counter() - t0,
                   "peak_mb": usage.ru_maxrss / 1024, "killed": killed}, fh)


if __name__ == "__main__":
    main()
