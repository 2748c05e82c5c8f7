"""The session hook in tests/conftest.py that finds the processes a test run left behind."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import MARKER, marked_processes

pytestmark = pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads Linux /proc")

SLEEP = [sys.executable, "-c", "import time; time.sleep(120)"]


def test_a_process_started_here_carries_the_marker_and_is_found():
    child = subprocess.Popen(SLEEP, start_new_session=True)  # detached, as an orphan would be
    try:
        found = marked_processes(os.environ[MARKER])
        assert child.pid in found and "time.sleep(120)" in found[child.pid]
        assert os.getpid() not in found
    finally:
        child.kill()
        child.wait()
    assert child.pid not in marked_processes(os.environ[MARKER])


def test_a_process_without_the_marker_is_not_ours():
    env = {k: v for k, v in os.environ.items() if k != MARKER}
    child = subprocess.Popen(SLEEP, env=env)
    try:
        assert child.pid not in marked_processes(os.environ[MARKER])
    finally:
        child.kill()
        child.wait()


LEAKS = """
import subprocess, sys
from pathlib import Path

def test_leaks_a_detached_process():
    child = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(120)"], start_new_session=True
    )
    Path("leaked.pid").write_text(str(child.pid))
"""


def test_a_test_run_kills_and_names_what_it_left_running(pytester, monkeypatch):
    pytester.makeconftest((Path(__file__).parent / "conftest.py").read_text())
    pytester.makepyfile(test_leak=LEAKS)
    monkeypatch.delenv(MARKER)  # the inner run is a session of its own
    monkeypatch.setenv("CREDIT_TEST_REAP_GRACE_S", "0.5")
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    result.assert_outcomes(passed=1)
    pid = int((pytester.path / "leaked.pid").read_text())
    result.stdout.fnmatch_lines(
        ["*processes the tests left running (killed)*", f"pid {pid}: *time.sleep(120)*"]
    )
    assert not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text()
