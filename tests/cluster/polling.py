"""Polling for the cluster tests, which watch real processes."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

from cluster.launch import ray_cluster


def wait_for(
    fn,
    timeout_s: float = 60.0,
    what: str = "condition",
    proc: subprocess.Popen | None = None,
    interval_s: float = 0.25,
    log: Path | None = None,
):
    """Poll fn() until it returns something truthy and return that; the deadline only guards
    against a hang. With `proc`, fail at once if that process exits meanwhile, quoting the end
    of its `log` file when one is given (what it said is the only clue a CI run leaves)."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = fn()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            said = ""
            if log is not None and log.exists():
                tail = log.read_text(errors="replace").splitlines()[-40:]
                said = f"; the end of {log}:\n" + "\n".join(tail)
            raise AssertionError(
                f"the process exited with {proc.returncode} waiting for {what}{said}"
            )
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(interval_s)


def session_members(sid: int) -> dict[int, str]:
    """pid -> command line of the live processes in session `sid` (a process started with
    `start_new_session=True` leads the session of its own pid, and what it starts, Ray's
    processes included, stays in it)."""
    table = ray_cluster.process_table()
    return {pid: p.cmd for pid, p in table.items() if p.sid == sid and p.state != "Z"}
