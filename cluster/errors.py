"""Errors every command may raise for bad command-line input (the CLI exits 2 on them)."""


class UsageError(ValueError):
    """Bad command-line input that argparse itself cannot catch."""
