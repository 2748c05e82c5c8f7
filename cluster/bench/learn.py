"""`credit bench learn`: env steps and wall seconds until each seed's greedy win rate first
reaches a target.

The seeds train together in one seed-batched `LocalTrainer` (E = seeds, one set of tensors),
with the run's shipped config plus `--set` overrides, and the learner's torch on the CPUs
this process may use less those other processes keep busy (`--threads 0`, the default:
`run.torch_threads=0`, `cluster.cpu`; training's own default is 1 thread, which is what
several runs side by side want; on the quiet 2-core machine two threads made the 3-seed QMIX
run about 1.5x faster, results/smac/README.md); every
`--test-interval` env steps each seed plays `run.test_episodes` greedy episodes. Training stops
when every seed has reached the target or at `--t-max`. Wall time counts everything from the
trainer's construction on (acting, updates and the evaluations themselves); the load average is
sampled at every evaluation, so a busy machine shows in the JSON.

`--compare-load` measures how the benchmark shares a CPU: it runs it twice in fresh
processes, first on the machine as it is, then beside `--load-procs` CPU-bound processes
(`credit bench load`: one per usable CPU by default), and prints both with the slowdown.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

from cluster import process
from cluster.bench.common import emit
from cluster.bench.load import LoadGenerator
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
        help="the learner's torch threads (run.torch_threads); 0: auto, the usable CPUs less "
        "those other processes keep busy, measured again every 10 s",
    )
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--out", help="also write the JSON here")
    p.add_argument(
        "--compare-load",
        action="store_true",
        help="run the benchmark quiet, then beside --load-procs CPU-bound processes, each in "
        "a fresh process; print both and the slowdown",
    )
    p.add_argument(
        "--load-procs",
        type=int,
        default=0,
        help="with --compare-load: busy processes (0: one per usable CPU)",
    )
    p.set_defaults(func=cmd_learn)


def cmd_learn(args: argparse.Namespace) -> int:
    if not 0.0 < args.target_win <= 1.0:
        raise UsageError(f"--target-win must be in (0, 1], got {args.target_win}")
    if args.seeds < 1:
        raise UsageError(f"--seeds must be >= 1, got {args.seeds}")
    if args.threads < 0:
        raise UsageError(f"--threads must be >= 0 (0: auto), got {args.threads}")
    if args.load_procs < 0:
        raise UsageError(
            f"--load-procs must be >= 0 (0: one per usable CPU), got {args.load_procs}"
        )
    if args.compare_load:
        return compare_load(args)
    overrides = [
        f"run.t_max={args.t_max}",
        f"run.test_interval={args.test_interval}",
        f"run.torch_threads={args.threads}",
        *args.set,  # a --set run.torch_threads=... comes later and wins
    ]
    cfg = load_train_config(args.algo, args.env, [], overrides)
    started = time.monotonic()
    process.configure(cfg.run)
    trainer = LocalTrainer(cfg, n_ensemble=args.seeds)
    if not trainer.core.ctx.info.has_wins:
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
            "torch_threads": cfg.run.torch_threads or "auto",
            "threads_used": process.threads_used(),
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
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


def compare_load(args: argparse.Namespace) -> int:
    """`--compare-load`: the benchmark quiet, then loaded, each in a fresh process."""
    argv = [sys.executable, "-m", "cluster.cli", "bench", "learn", "--env", args.env]
    argv += ["--algo", args.algo, "--target-win", str(args.target_win), "--seeds", str(args.seeds)]
    argv += ["--t-max", str(args.t_max), "--test-interval", str(args.test_interval)]
    argv += ["--threads", str(args.threads)]
    for kv in args.set:
        argv += ["--set", kv]

    def measure() -> dict:
        done = subprocess.run(argv, capture_output=True, text=True)
        if done.returncode != 0:
            raise UsageError(f"{' '.join(argv[2:])} failed: {done.stderr[-2000:]}")
        got = json.loads(done.stdout)
        return {k: v for k, v in got.items() if k not in ("command", "time_utc", "machine")}

    quiet = measure()
    with LoadGenerator(args.load_procs) as load:
        loaded = measure()

    def ratio(key: str) -> float | None:
        a, b = quiet[key], loaded[key]
        return None if not a or b is None else round(b / a, 2)

    per_step = [r["total_wall_s"] / max(1, r["t_env_end"]) for r in (quiet, loaded)]
    emit(
        "learn_compare_load",
        {
            "load_procs": load.procs,
            "load_cpu_s": load.cpu_s,
            "slowdown_median_wall": ratio("median_wall_s"),
            "slowdown_wall_per_env_step": round(per_step[1] / per_step[0], 2),
            "quiet": quiet,
            "loaded": loaded,
        },
        args.out,
    )
    return 0
