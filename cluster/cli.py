"""The `credit` command line. Each subcommand lives in `cluster/commands/<name>.py` and
exposes `register(subparsers)`; the list below is the whole registry of commands."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from cluster.errors import Terminated

log = logging.getLogger("credit")

DESCRIPTION = (
    "credit trains cooperative multi-agent reinforcement learning algorithms (RDN, EM-CAC "
    "and their baselines) on matrix games, the built-in skirmish simulator or StarCraft II "
    "SMAC, in one process or on a local multi-process Ray cluster. Start with `credit demo`. "
    "Each command below says what it writes; `credit COMMAND --help` lists its options. "
    "Training runs write under --out (runs/... by default); run-time state (the Ray "
    "cluster, Prometheus, the file-SD links of live runs) lives in ~/.credit/, or in "
    "$CREDIT_STATE_DIR when that is set."
)

# cluster/commands/<name>.py, in `credit --help`'s order. A command's module is imported only
# when it is run (or for the full help), so `credit buffer serve` does not load torch or numba.
COMMANDS = (
    "demo",
    "train",
    "repro",
    "report",
    "sweep",
    "env",
    "inspect",
    "bench",
    "buffer",
    "cluster",
    "metrics",
    "dashboard",
)
# (module, class, exit status) of the errors `main` reports in one line; a class is looked up
# only when its module is loaded, for an exception of it can come from nowhere else.
ERRORS = (
    ("cluster.config.schema", "ConfigError", 2),
    ("actors.envs.base", "EnvError", 2),
    ("cluster.errors", "UsageError", 2),
    ("learner.common", "NonFiniteLossError", 3),
    ("cluster.launch.ray_cluster", "ClusterError", 1),  # e.g. a repro pair lost too often
)


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """`credit`'s parser with every command, or with only the command `only`."""
    parser = argparse.ArgumentParser(prog="credit", description=DESCRIPTION)
    parser.add_argument("-v", "--verbose", action="store_true", help="log at debug level")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS if only is None else (only,):
        importlib.import_module(f"cluster.commands.{name}").register(sub)
    return parser


def _command(argv: list[str]) -> str | None:
    """The command `argv` runs, when it names one (the first word that is not an option)."""
    word = next((w for w in argv if not w.startswith("-")), None)
    return word if word in COMMANDS else None


def _status(e: BaseException) -> int | None:
    """`main`'s exit status for an error it reports in one line; None for any other."""
    for module, cls, status in ERRORS:
        loaded = sys.modules.get(module)
        if loaded is not None and isinstance(e, getattr(loaded, cls)):
            return status
    return None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_command(argv))
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return int(args.func(args) or 0)
    except Terminated:  # SIGTERM to a process with a private Ray instance (`ray_cluster`)
        print("credit: terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("credit: interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        status = _status(e)
        if status is None:
            raise
        print(f"credit: error: {e}", file=sys.stderr)
        return status


if __name__ == "__main__":
    sys.exit(main())
