"""The `credit` command line. Each subcommand lives in `cluster/commands/<name>.py` and
exposes `register(subparsers)`; the list below is the whole registry of commands."""

from __future__ import annotations

import argparse
import logging
import sys

from actors.envs.base import EnvError
from cluster.commands import bench as bench_cmd
from cluster.commands import buffer as buffer_cmd
from cluster.commands import cluster as cluster_cmd
from cluster.commands import dashboard as dashboard_cmd
from cluster.commands import demo as demo_cmd
from cluster.commands import env as env_cmd
from cluster.commands import inspect as inspect_cmd
from cluster.commands import metrics as metrics_cmd
from cluster.commands import report as report_cmd
from cluster.commands import repro as repro_cmd
from cluster.commands import sweep as sweep_cmd
from cluster.commands import train as train_cmd
from cluster.config.schema import ConfigError
from cluster.errors import UsageError
from cluster.launch.ray_cluster import ClusterError
from learner.common import NonFiniteLossError

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

COMMANDS = [
    demo_cmd,
    train_cmd,
    repro_cmd,
    report_cmd,
    sweep_cmd,
    env_cmd,
    inspect_cmd,
    bench_cmd,
    buffer_cmd,
    cluster_cmd,
    metrics_cmd,
    dashboard_cmd,
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="credit", description=DESCRIPTION)
    parser.add_argument("-v", "--verbose", action="store_true", help="log at debug level")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in COMMANDS:
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return int(args.func(args) or 0)
    except (ConfigError, EnvError, UsageError) as e:
        print(f"credit: error: {e}", file=sys.stderr)
        return 2
    except NonFiniteLossError as e:
        print(f"credit: error: {e}", file=sys.stderr)
        return 3
    except ClusterError as e:  # e.g. a repro pair lost more often than it may be retried
        print(f"credit: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("credit: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
