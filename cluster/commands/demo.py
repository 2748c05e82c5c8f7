"""`credit demo`: watch QMIX learn skirmish/3m on the local multi-process cluster.

Starts the live dashboard, trains QMIX on the built-in skirmish simulator's 3m map with the
local multi-process cluster (a private Ray instance on 127.0.0.1, Ray rollout actors, the
buffer service over TCP, this process as the learner), printing a progress line at every
greedy evaluation. It keeps the policy of its best greedy evaluation as well as the final one
(run.keep_best); then it evaluates both on the same fresh episodes, writes a learning-curve
PNG and a GIF of the kept policy winning, prints where they are, and keeps the
dashboard up until Ctrl-C when it runs on a terminal (`--no-wait`, or a stdin that is not a
terminal, closes it at once).
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from actors.envs.registry import make_vec_env
from cluster.commands import add_command, train
from cluster.dashboard import report as demo_report
from cluster.dashboard.server import DashboardConfig, DashboardServer, ExporterSource
from cluster.errors import UsageError
from cluster.metrics.discovery import read_file_sd

log = logging.getLogger(__name__)

# The demo's budget, measured on the project's 2-core machine with 3 runs each
# (results/demo/README.md): QMIX with its shipped skirmish settings (feed-forward agents, a GRU
# update costs about 4x more, and Q(lambda = 0.6) targets; envs/skirmish.qmix.yaml): every run
# ended at 0.98-1.00 over 100 fresh greedy episodes after 60k env steps (without lambda:
# 0.80-1.00).
T_MAX = 60_000
TEST_INTERVAL = 2_500


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "demo",
        "Train QMIX (feed-forward agents, Q(lambda) targets) on skirmish/3m with the local "
        "multi-process cluster while the live dashboard shows it, then print the greedy "
        "win rate of the policy kept at its best evaluation and of the final one; writes "
        "OUT/config.yaml, metrics.jsonl, summary.json, checkpoint/ (final), best/ (kept), "
        "buffer/, learning_curve.png and policy.gif (the kept policy playing).",
    )
    p.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    p.add_argument("--algo", default="qmix", help="algorithm (default qmix)")
    p.add_argument("--env", default="skirmish/3m", help="a skirmish env id (default skirmish/3m)")
    p.add_argument("--actors", type=int, default=2, help="Ray rollout actors (default 2)")
    p.add_argument("--t-max", type=int, default=T_MAX, help=f"env steps (default {T_MAX})")
    p.add_argument(
        "--test-interval",
        type=int,
        default=TEST_INTERVAL,
        help=f"env steps between greedy evaluations (default {TEST_INTERVAL})",
    )
    p.add_argument(
        "--episodes",
        type=int,
        default=100,
        help="fresh greedy episodes for each saved policy's win rate (default 100)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override on top of the shipped settings; repeatable",
    )
    p.add_argument("--dashboard-port", type=int, default=0, help="dashboard port (0 = free)")
    p.add_argument(
        "--no-wait",
        action="store_true",
        help="close the dashboard when training ends instead of waiting for Ctrl-C",
    )
    p.set_defaults(func=cmd_demo)


def _targets(path: Path) -> list[str]:
    return [f"{h}:{p}" for h, p in read_file_sd(path)] if path.exists() else []


def cmd_demo(args: argparse.Namespace) -> int:
    if not args.env.startswith("skirmish/"):
        raise UsageError(f"--env must be a skirmish map (the GIF draws one), got {args.env!r}")
    if args.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {args.episodes}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    # The charts keep the whole run (a few minutes) while the dashboard waits after it.
    dash_cfg = DashboardConfig(port=args.dashboard_port, range_s=900.0, history_s=1800.0)
    source = ExporterSource(
        functools.partial(_targets, out / "targets.json"), dash_cfg, label="demo", run_dir=out
    )
    dashboard = DashboardServer(dash_cfg, source).start()
    print(f"live dashboard: {dashboard.url}", flush=True)
    try:
        _compile_simulator(args.env)
        code = _train(args, out)
        if code:
            return code
        print("evaluating the trained policy and drawing its curve and a replay...", flush=True)
        report = demo_report.write_report(out, episodes=args.episodes)
        _print_report(args, out, report)
        _wait(args, dashboard.url)
    finally:
        dashboard.close()
    return 0


def _compile_simulator(env_id: str) -> None:
    """Play one step of `env_id` here first, so that the simulator's numba kernels are
    compiled once and cached (numba's cache=True) before the Ray actors start; otherwise, in
    a fresh checkout, the learner and every actor compile them at the same time on the same
    cores."""
    started = time.perf_counter()
    venv = make_vec_env(env_id, 1, seed=0)
    venv.reset()
    venv.step(venv.get_avail_actions().argmax(-1), np.ones(1, bool))  # first available action
    venv.get_obs(), venv.get_state()
    log.info("simulator ready in %.1f s", time.perf_counter() - started)


def _train(args: argparse.Namespace, out: Path) -> int:
    parser = argparse.ArgumentParser()
    train.register(parser.add_subparsers())
    argv = ["train", "--mode", "cluster", "--actors", str(args.actors), "--algo", args.algo]
    argv += ["--env", args.env, "--t-max", str(args.t_max), "--out", str(out)]
    # keep the policy of the best greedy evaluation too (best/): QMIX's greedy policy on 3m
    # still swings between evaluations near 60k steps (results/demo/README.md)
    sets = [f"run.test_interval={args.test_interval}", "run.keep_best=true", *args.set]
    for item in sets:
        argv += ["--set", item]
    return train.cmd_train(parser.parse_args(argv))


def _print_report(args: argparse.Namespace, out: Path, report: demo_report.DemoReport) -> None:
    summary = json.loads((out / "summary.json").read_text())
    first = json.loads((out / "metrics.jsonl").read_text().splitlines()[0])
    shown, final, n = report.shown, report.final, report.episodes
    line = (
        f"\ndemo finished: {args.algo.upper()} on {args.env} reached a greedy win rate of "
        f"{shown.win_rate:.2f} ({round(shown.win_rate * n)} of {n} fresh episodes, mean return "
        f"{shown.return_mean:.1f})"
    )
    kept = report.best_evaluation
    if report.best is None or kept is None:
        line += f" after {final.t_env:,} env steps."
    else:
        score = f"{kept.get('test_won_mean', 0.0):.2f} over {report.evaluation_episodes} episodes"
        if report.best.t_env == final.t_env:
            line += (
                f" after {final.t_env:,} env steps; its evaluation at the end of training "
                f"({score}) was its best, so the kept policy is the final one."
            )
        else:
            line += (
                f" with the policy kept at its best greedy evaluation during training "
                f"({shown.t_env:,} env steps: win rate {score}); the final policy, after "
                f"{final.t_env:,} env steps, won {round(final.win_rate * n)} of {n}."
            )
    print(
        f"{line} Training took {summary['wall_s']:.0f} s with {args.actors} Ray rollout actors "
        f"({first['wall_s']:.0f} s of it starting the actors, up to the first evaluation)."
    )
    print(f"  learning curve:             {report.curve_png}")
    what = "the trained policy winning:" if report.gif_won else "the trained policy (lost):"
    print(f"  {what:<27} {report.gif}")
    kept_folder = ", best/ (the kept one)" if report.best is not None else ""
    print(
        f"  everything else in {out}/: config.yaml, metrics.jsonl, summary.json, checkpoint/ "
        f"(the final policy){kept_folder}"
    )


def _wait(args: argparse.Namespace, url: str) -> None:
    if args.no_wait:
        return
    if not sys.stdin.isatty():
        print("stdin is not a terminal, so the dashboard closes now (as with --no-wait)")
        return
    print(f"\nthe dashboard stays up at {url}; press Ctrl-C to stop it", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        print("dashboard stopped")
