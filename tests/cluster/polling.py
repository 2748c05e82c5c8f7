"""Polling for the cluster tests, which watch real processes."""

from __future__ import annotations

import subprocess
import time


def wait_for(
    fn,
    timeout_s: float = 60.0,
    what: str = "condition",
    proc: subprocess.Popen | None = None,
    interval_s: float = 0.25,
):
    """Poll fn() until it returns something truthy and return that; the deadline only guards
    against a hang. With `proc`, fail at once if that process exits meanwhile."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = fn()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"the process exited with {proc.returncode} waiting for {what}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(interval_s)
