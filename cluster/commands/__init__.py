"""The `credit` subcommands, one module each (registered in `cluster.cli.COMMANDS`)."""

from __future__ import annotations

import argparse


def add_command(sub: argparse._SubParsersAction, name: str, text: str) -> argparse.ArgumentParser:
    """A subcommand whose line in its parent's list and whose own `--help` both read `text`:
    whole sentences that say what the command does and what it writes."""
    return sub.add_parser(name, help=text, description=text)
