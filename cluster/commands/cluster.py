"""`credit cluster up|status|down`: a local multi-process Ray cluster on loopback."""

from __future__ import annotations

import argparse

from cluster.commands import add_command
from cluster.errors import UsageError
from cluster.launch import ray_cluster


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "cluster",
        "Start, inspect or stop a local Ray cluster on 127.0.0.1; its state lives in "
        "~/.credit/cluster/.",
    )
    csub = p.add_subparsers(dest="cluster_command", required=True, metavar="CLUSTER_COMMAND")
    up = add_command(
        csub,
        "up",
        "Start a Ray head node and its worker processes; writes "
        "~/.credit/cluster/state.json and the Ray token there.",
    )
    up.add_argument("--num-cpus", type=int, default=2, help="CPUs the cluster offers (default 2)")
    up.add_argument("--port", type=int, default=6379, help="GCS port (default 6379)")
    up.add_argument("--host", default=ray_cluster.LOOPBACK, help="node address (default 127.0.0.1)")
    up.set_defaults(func=cmd_up)
    st = add_command(
        csub,
        "status",
        "Print the cluster's nodes and resources; writes nothing.",
    )
    st.set_defaults(func=cmd_status)
    dn = add_command(
        csub,
        "down",
        "Stop the cluster that `up` started (only its processes) and remove its state file.",
    )
    dn.set_defaults(func=cmd_down)


def cmd_up(args: argparse.Namespace) -> int:
    try:
        state = ray_cluster.up(args.num_cpus, args.port, args.host)
    except ray_cluster.ClusterError as e:
        raise UsageError(str(e)) from None
    print(f"Ray cluster up at {state.address} ({state.num_cpus} CPUs); train on it with:")
    print("  credit train --mode cluster --address auto --actors 2 ...")
    print("  credit repro matrix --address auto --out DIR   (or any repro experiment)")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    print(ray_cluster.status())
    return 0


def cmd_down(args: argparse.Namespace) -> int:
    try:
        stopped = ray_cluster.down()
    except ray_cluster.ClusterError as e:
        raise UsageError(str(e)) from None
    print(f"Ray cluster stopped ({stopped} processes)" if stopped else "no credit Ray cluster up")
    return 0
