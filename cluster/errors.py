"""Errors every command may raise for bad command-line input (the CLI exits 2 on them)."""


class UsageError(ValueError):
    """Bad command-line input that argparse itself cannot catch."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in a process that owns a private Ray instance so that it shuts down
    as after Ctrl-C (the CLI exits 143 on it) instead of leaving Ray's processes behind."""
