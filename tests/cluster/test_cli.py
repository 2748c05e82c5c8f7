"""The command registry: every command module is reachable from `credit`."""

import pkgutil

import cluster.commands
from cluster.cli import COMMANDS, build_parser


def test_every_command_module_is_registered():
    modules = {m.name for m in pkgutil.iter_modules(cluster.commands.__path__)}
    registered = {c.__name__.rsplit(".", 1)[1] for c in COMMANDS}
    assert modules == registered


def test_help_lists_the_commands(capsys):
    parser = build_parser()
    text = parser.format_help()
    for name in (
        "train",
        "repro",
        "cluster",
        "buffer",
        "metrics",
        "dashboard",
        "env",
        "bench",
        "demo",
    ):
        assert name in text
