"""`tests/conftest.py` gives SIGINT back to a test run that a shell's `&` started ignoring it,
so that the children the tests stop with SIGINT (Ctrl-C) stop."""

from __future__ import annotations

import signal
import subprocess
import sys

from tests.conftest import restore_ctrl_c

SAYS_HANDLER = """
import signal
handler = signal.getsignal(signal.SIGINT)
print("interrupts" if handler is signal.default_int_handler else f"not: {handler!r}")
"""


def _child_handler() -> str:
    out = subprocess.run([sys.executable, "-c", SAYS_HANDLER], capture_output=True, text=True)
    return out.stdout.strip()


def test_children_of_a_backgrounded_test_run_stop_on_sigint():
    """With SIGINT ignored here (as `&` leaves it), a child ignores it too; after
    `restore_ctrl_c` a child raises KeyboardInterrupt on it."""
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        assert _child_handler().startswith("not:")
        restore_ctrl_c()
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        assert _child_handler() == "interrupts"
    finally:
        signal.signal(signal.SIGINT, before)
