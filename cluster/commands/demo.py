"""`credit demo`: the main job on the embedded default, small enough to watch.

Starts the live dashboard, then trains RDN on the built-in skirmish simulator's 3m map with
the local multi-process cluster (a private Ray instance on 127.0.0.1, rollout actors, the
buffer service, this process as the learner), and prints where everything is.
"""

from __future__ import annotations

import argparse
import functools
import logging
from pathlib import Path

from cluster.commands import add_command, train
from cluster.dashboard.server import DashboardConfig, DashboardServer, ExporterSource
from cluster.metrics import read_file_sd

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "demo",
        "Train RDN on skirmish/3m with the local multi-process cluster while the live "
        "dashboard shows it; writes OUT/config.yaml, metrics.jsonl, summary.json, "
        "checkpoint/ and buffer/.",
    )
    p.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    p.add_argument("--env", default="skirmish/3m", help="env id (default skirmish/3m)")
    p.add_argument("--actors", type=int, default=2, help="rollout actors (default 2)")
    p.add_argument("--t-max", type=int, default=20_000, help="env steps (default 20000)")
    p.add_argument("--dashboard-port", type=int, default=0, help="dashboard port (0 = free)")
    p.set_defaults(func=cmd_demo)


def _targets(path: Path) -> list[str]:
    return [f"{h}:{p}" for h, p in read_file_sd(path)] if path.exists() else []


def cmd_demo(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    dash_cfg = DashboardConfig(port=args.dashboard_port)
    source = ExporterSource(
        functools.partial(_targets, out / "targets.json"), dash_cfg, label="demo"
    )
    dashboard = DashboardServer(dash_cfg, source).start()
    print(f"live dashboard: {dashboard.url}", flush=True)
    parser = argparse.ArgumentParser()
    train.register(parser.add_subparsers())
    argv = ["train", "--mode", "cluster", "--actors", str(args.actors), "--algo", "rdn"]
    argv += ["--env", args.env, "--t-max", str(args.t_max), "--out", str(out)]
    argv += ["--set", f"run.test_interval={max(1, args.t_max // 10)}"]
    try:
        code = train.cmd_train(parser.parse_args(argv))
    finally:
        dashboard.close()
    if code:
        return code
    print(f"\ndemo finished; results in {out}/: summary.json, metrics.jsonl, checkpoint/, buffer/")
    print("more: credit repro matrix --seeds 8 --out results/matrix   (seed Fig. 5.3)")
    return 0
