"""Session-wide hooks.

* The test tiers (tests/README.md): after a run of the default tier, name the tests that took
  long enough to belong in `make test-slow`, so the rule is seen where it is broken.
* Processes left behind: every process the tests start inherits `MARKER` in its environment;
  at the end of the session those still running whose parent has gone (a Ray agent orphaned
  by a killed driver, a server whose launcher exited without stopping it) are killed and
  named, so that a test run never leaves work behind."""

from __future__ import annotations

import os
import signal
import time
import uuid
from pathlib import Path

import pytest

from cluster.launch.ray_cluster import Proc, process_table, with_descendants

# A default-tier test this long on the project's 2-core machine belongs in the slow tier
# (tests/README.md). Reported, never asserted: timings on a shared machine drift.
REPORT_OVER_S = float(os.environ.get("CREDIT_TEST_REPORT_OVER_S", "20"))

_durations: dict[str, float] = {}
_kept: dict[str, str] = {}  # nodeid -> why it stays in the default tier though long


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.when != "teardown" and not item.get_closest_marker("slow"):
        _durations[item.nodeid] = _durations.get(item.nodeid, 0.0) + report.duration
        kept = item.get_closest_marker("default_tier")
        if kept is not None:
            _kept[item.nodeid] = kept.kwargs.get("reason") or (kept.args or ("",))[0]


def pytest_terminal_summary(terminalreporter):
    if _left:
        terminalreporter.section("processes the tests left running (killed)")
        for pid, cmd in _left:
            terminalreporter.write_line(f"pid {pid}: {cmd[:160]}")
    long = sorted(((s, n) for n, s in _durations.items() if s > REPORT_OVER_S), reverse=True)
    kept = [(s, n) for s, n in long if n in _kept]
    long = [(s, n) for s, n in long if n not in _kept]
    if kept:
        terminalreporter.section("long tests kept in the default tier on purpose (tests/README.md)")
        for seconds, nodeid in kept:
            terminalreporter.write_line(f"{seconds:6.1f} s  {nodeid}  ({_kept[nodeid]})")
    if long:
        terminalreporter.section("tests that belong in the slow tier (tests/README.md)")
        for seconds, nodeid in long:
            terminalreporter.write_line(f"{seconds:6.1f} s  {nodeid}  (not marked slow)")


pytest_plugins = ["pytester"]  # test_leftover_processes.py, test_tier_report.py: runs of their own

MARKER = "CREDIT_TEST_SESSION"
# How long processes still shutting down (ray.shutdown's own SIGTERM, then SIGKILL) get.
GRACE_S = float(os.environ.get("CREDIT_TEST_REAP_GRACE_S", "10"))
_left: list[tuple[int, str]] = []


def restore_ctrl_c() -> None:
    """Give SIGINT back its KeyboardInterrupt handler if the shell set it to "ignore".

    A shell that runs a command in the background (`make test-slow &`, `nohup ... &` in a
    script) sets SIGINT to ignored, every child inherits that, and Python installs its
    KeyboardInterrupt handler only where SIGINT is at its default at startup. The tests that
    stop a child with SIGINT, as a user stops it with Ctrl-C, would then wait on a process
    that ignores it (a cluster `credit train` ran on for 13 minutes so on 2026-12-07). A
    Python-level handler is reset to the default on exec, so every child of this process
    starts with SIGINT at its default again."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_configure(config):
    os.environ.setdefault(MARKER, f"{os.getpid()}-{uuid.uuid4().hex}")
    restore_ctrl_c()
    config.addinivalue_line(
        "markers",
        "default_tier(reason): long, but kept in `make test` on purpose (tests/README.md); "
        "the report of long tests lists it apart, with its reason",
    )


def marked_processes(value: str) -> dict[int, Proc]:
    """pid -> `Proc` of the processes other than this one whose environment holds
    MARKER=value (processes of other users cannot be read, and are not ours)."""
    needle = f"{MARKER}={value}".encode()
    table = process_table()
    found = {}
    for pid, proc in table.items():
        try:
            marked = needle in Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        except OSError:  # exited meanwhile, or not ours
            continue
        if marked and pid != os.getpid():
            found[pid] = proc
    return found


def left_behind(procs: dict[int, Proc], me: int) -> dict[int, str]:
    """The processes of `procs` (from `marked_processes`) that lost the parent that started
    them (it exited, so they belong to init now), with everything below them. This process's
    own children are not among them: they are its helpers (multiprocessing's resource
    tracker, wandb's service), which end when it ends."""
    orphans = {pid for pid, p in procs.items() if p.ppid != me and p.ppid not in procs}
    return {pid: procs[pid].cmd for pid in sorted(with_descendants(procs, orphans))}


def pytest_sessionfinish(session):
    value = os.environ.get(MARKER, "")
    if not value.startswith(f"{os.getpid()}-") or not Path("/proc").is_dir():
        return  # a pytest started by a test (the marker is the outer session's), or not Linux
    deadline = time.monotonic() + GRACE_S
    while (left := left_behind(marked_processes(value), os.getpid())) and (
        time.monotonic() < deadline
    ):
        time.sleep(0.5)
    for pid, cmd in left.items():
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            continue
        _left.append((pid, cmd))
