"""The helper the Ctrl-C tests start their children with."""

from __future__ import annotations

import signal
import subprocess
import sys

from tests.cluster.ctrl_c import sigint_default

SAYS_HANDLER = """
import signal
handler = signal.getsignal(signal.SIGINT)
print("interrupts" if handler is signal.default_int_handler else f"not: {handler!r}")
"""


def _child_handler(**popen) -> str:
    out = subprocess.run(
        [sys.executable, "-c", SAYS_HANDLER], capture_output=True, text=True, **popen
    )
    return out.stdout.strip()


def test_a_child_of_a_backgrounded_runner_gets_keyboard_interrupt_back():
    """With SIGINT ignored here (as a shell's `&` leaves it), a plain child ignores it too;
    one started with `sigint_default` raises KeyboardInterrupt on it."""
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        assert _child_handler().startswith("not:")
        assert _child_handler(preexec_fn=sigint_default) == "interrupts"
    finally:
        signal.signal(signal.SIGINT, before)
