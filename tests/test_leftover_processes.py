"""The session hook in tests/conftest.py that finds the processes a test run left behind."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cluster.launch.ray_cluster import Proc
from tests.conftest import MARKER, left_behind, marked_processes

pytestmark = pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads Linux /proc")

SLEEP = "import time; time.sleep(120)"
# A launcher that starts a sleeper and exits without stopping it, as a killed Ray driver
# leaves its agents: the sleeper's parent is gone. Prints the sleeper's pid.
ORPHAN = (
    "import subprocess, sys; "
    f"print(subprocess.Popen([sys.executable, '-c', {SLEEP!r}], start_new_session=True, "
    "stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).pid)"
)


def _orphan() -> int:
    return int(subprocess.check_output([sys.executable, "-c", ORPHAN], text=True))


def _kill(pid: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, 9)


def test_an_orphan_is_left_behind_and_a_child_of_this_process_is_not():
    child = subprocess.Popen([sys.executable, "-c", SLEEP])  # a helper this process ends
    orphan = _orphan()
    try:
        procs = marked_processes(os.environ[MARKER])
        assert procs[child.pid].ppid == os.getpid()
        assert procs[child.pid].cmd == f"{sys.executable} -c {SLEEP}"
        assert orphan in procs and os.getpid() not in procs
        left = left_behind(procs, os.getpid())
        assert orphan in left and child.pid not in left
    finally:
        child.kill()
        child.wait()
        _kill(orphan)


def test_what_is_below_an_orphan_is_left_behind_too():
    tree = {10: (1, "orphan"), 11: (10, "its child"), 12: (11, "grandchild"), 20: (99, "mine")}
    procs = {pid: Proc(ppid, 0, 0, "S", cmd) for pid, (ppid, cmd) in tree.items()}
    assert left_behind(procs, me=99) == {10: "orphan", 11: "its child", 12: "grandchild"}


def test_a_process_without_the_marker_is_not_ours():
    env = {k: v for k, v in os.environ.items() if k != MARKER}
    child = subprocess.Popen([sys.executable, "-c", SLEEP], env=env)
    try:
        assert child.pid not in marked_processes(os.environ[MARKER])
    finally:
        child.kill()
        child.wait()


LEAKS = f"""
import subprocess, sys
from pathlib import Path

def test_leaves_an_orphan():
    pid = subprocess.check_output([sys.executable, "-c", {ORPHAN!r}], text=True)
    Path("leaked.pid").write_text(pid)
"""


def test_a_test_run_kills_and_names_what_it_left_running(pytester, monkeypatch):
    pytester.makeconftest((Path(__file__).parent / "conftest.py").read_text())
    pytester.makepyfile(test_leak=LEAKS)
    monkeypatch.delenv(MARKER)  # the inner run is a session of its own
    monkeypatch.setenv("CREDIT_TEST_REAP_GRACE_S", "0.5")
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    result.assert_outcomes(passed=1)
    pid = int((pytester.path / "leaked.pid").read_text())
    try:
        result.stdout.fnmatch_lines(
            ["*processes the tests left running (killed)*", f"pid {pid}: *time.sleep(120)*"]
        )
        assert not Path(f"/proc/{pid}").exists() or " Z " in Path(f"/proc/{pid}/stat").read_text()
    finally:
        _kill(pid)
