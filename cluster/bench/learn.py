"""`credit bench learn`: env steps and wall seconds until each seed's greedy win rate first
reaches a target.

The seeds train together in one seed-batched `LocalTrainer` (E = seeds, one set of tensors),
with the run's shipped config plus `--set` overrides, and the learner's torch on every CPU
this process may use (`--threads`; training's own default, `run.torch_threads`, is 1 thread,
which is what several runs side by side want; on the 2-core machine two threads made the
3-seed QMIX run about 1.5x faster, results/smac/README.md); every
`--test-interval` env steps each seed plays `run.test_episodes` greedy episodes. Training stops
when every seed has reached the target or at `--t-max`. Wall time counts everything from the
trainer's construction on (acting, updates and the evaluations themselves); the load average is
sampled at every evaluation, so a busy machine shows in the JSON.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from cluster.bench.common import emit
from cluster.commands import add_command
from cluster.config.train import load_train_config
from cluster.errors import UsageError
from cluster.launch.local import LocalTrainer


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "learn",
        "Train seeds until they reach a win rate and print the env steps and wall time as"
        " JSON; --out also writes it.",
    )
    p.add_argument("--env", default="skirmish/3m")
    p.add_argument("--algo", default="qmix")
    p.add_argument("--target-win", type=float, default=0.95, help="greedy win rate to reach")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--t-max", type=int, default=200_000, help="give up after this many steps")
    p.add_argument("--test-interval", type=int, default=2000, help="env steps between evaluations")
    p.add_argument(
        "--threads",
        type=int,
        default=0,
        help="the learner's torch threads (run.torch_threads); 0: every CPU this process may use",
    )
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--out", help="also write the JSON here")
    p.set_defaults(func=cmd_learn)


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def cmd_learn(args: argparse.Namespace) -> int:
    if not 0.0 < args.target_win <= 1.0:
        raise UsageError(f"--target-win must be in (0, 1], got {args.target_win}")
    if args.seeds < 1:
        raise UsageError(f"--seeds must be >= 1, got {args.seeds}")
    if args.threads < 0:
        raise UsageError(f"--threads must be >= 0 (0: every usable CPU), got {args.threads}")
    threads = args.threads or usable_cpus()
    overrides = [
        f"run.t_max={args.t_max}",
        f"run.test_interval={args.test_interval}",
        f"run.torch_threads={threads}",
        *args.set,  # a --set run.torch_threads=... comes later and wins
    ]
    cfg = load_train_config(args.algo, args.env, [], overrides)
    torch.set_num_threads(1)
    started = time.monotonic()
    trainer = LocalTrainer(cfg, n_ensemble=args.seeds)
    if not trainer.core.info.has_wins:
        raise UsageError(f"{args.env} reports no battle wins; bench learn needs a map that does")
    steps: list[int | None] = [None] * args.seeds
    wall: list[float | None] = [None] * args.seeds
    loads: list[float] = []
    curve: list[dict] = []

    def on_eval(records) -> None:
        loads.append(os.getloadavg()[0])
        now = round(time.monotonic() - started, 2)
        curve.append({"t_env": records[0].t_env, "wall_s": now, "won": []})
        for r in records:
            won = r.test_won_mean or 0.0
            curve[-1]["won"].append(won)
            if steps[r.member] is None and won >= args.target_win - 1e-9:
                steps[r.member], wall[r.member] = r.t_env, now

    trainer.train(on_eval=on_eval, stop=lambda: all(s is not None for s in steps))

    def median(xs: list) -> float | None:
        """Median with a seed that never reached the target counted as infinitely late."""
        m = float(np.median([np.inf if x is None else x for x in xs]))
        return None if np.isinf(m) else m

    emit(
        "learn",
        {
            "env": args.env,
            "algo": args.algo,
            "target_win": args.target_win,
            "seeds": args.seeds,
            "test_interval": args.test_interval,
            "test_episodes": cfg.run.test_episodes,
            "overrides": args.set,
            "torch_threads": cfg.run.torch_threads,
            "env_steps": steps,
            "wall_s": wall,
            "median_env_steps": median(steps),
            "median_wall_s": median(wall),
            "t_env_end": trainer.core.t_env,
            "total_wall_s": round(time.monotonic() - started, 2),
            "updates": trainer.core.learner.updates,
            "load_avg_1m": {
                "min": min(loads, default=None),
                "mean": round(float(np.mean(loads)), 2) if loads else None,
                "max": max(loads, default=None),
            },
            "curve": curve,
        },
        args.out,
    )
    return 0
