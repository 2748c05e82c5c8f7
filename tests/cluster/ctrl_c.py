"""Children that a test stops with SIGINT, as a user stops them with Ctrl-C.

A shell that runs a command in the background (`make test-slow &`, `nohup ... &` in a
script) sets SIGINT to "ignore" for it, every child inherits that, and Python installs its
KeyboardInterrupt handler only where SIGINT is at its default at startup. A test that sends
SIGINT to a child started from such a pytest would wait on a process that ignores it (a
cluster `credit train` ran on for 13 minutes so on 2026-12-07). Pass `preexec_fn=sigint_default`
to `subprocess.Popen` for every child a test means to interrupt.
"""

from __future__ import annotations

import signal


def sigint_default() -> None:
    """In the child, before exec: SIGINT back to its default, so Python raises
    KeyboardInterrupt on it whatever the test runner's shell did."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
