"""`credit bench train`: env steps per second of the real training loop, and where its time
went.

Runs `LocalTrainer` (the one loop, `cluster.loop.TrainLoop`) for `--steps` env steps of
`--seeds` seed-batched members with the run's shipped config plus `--set` overrides, with the
loop's section timers (`learner.timers`) switched on. The parts are exclusive seconds:

    env          the envs' step, observations, states and available actions (training rounds)
    acting       the agents' forward and action selection while training
    act_other    the rest of a round: episode arrays, inserting into the tables
    sampling     drawing batches from the tables (rate limiter, stacking episodes)
    batching     the batch's arrays turned into tensors (`TensorBatch.from_episodes`)
    forward      the update less batching, backward and optimiser: the networks' forward,
                 targets and losses, the target-network copy
    backward     `loss.backward()`
    optimiser    per-member gradient clipping and the optimiser's step
    evaluation   the greedy test episodes (their env steps included)
    checkpoint   writing checkpoints (`--save-interval`; none by default)
    other        the rest of the loop (counters, progress)

The parts sum to the total wall time of `train` (`parts_sum_s` against `total_s`). The load
average before and after is in the JSON: compare runs side by side, not across machines.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from cluster.bench.common import emit
from cluster.commands import add_command
from cluster.config.train import load_train_config
from cluster.errors import UsageError
from cluster.launch.local import LocalTrainer
from cluster.process import configure
from learner.timers import TIMERS

# part name -> the section paths (exclusive seconds) that make it up
PARTS: dict[str, tuple[str, ...]] = {
    "env": ("act/env",),
    "acting": ("act/policy",),
    "act_other": ("act",),
    "sampling": ("sample",),
    "batching": ("update/batch",),
    "forward": ("update",),
    "backward": ("update/backward",),
    "optimiser": ("update/optimiser",),
    "evaluation": ("periodic", "periodic/env", "periodic/policy"),
    "checkpoint": ("periodic/checkpoint",),
}


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "train",
        "Run the real training loop for --steps env steps and print env steps per second and "
        "where the time went as JSON; --out also writes it.",
    )
    p.add_argument("--env", default="skirmish/3m")
    p.add_argument("--algo", default="qmix")
    p.add_argument("--seeds", type=int, default=1, help="seed-batched members (n_ensemble)")
    p.add_argument("--steps", type=int, default=5000, help="env steps per member (run.t_max)")
    p.add_argument(
        "--test-interval", type=int, default=0, help="env steps between evaluations (0: config's)"
    )
    p.add_argument(
        "--save-interval",
        type=int,
        default=0,
        help="env steps between checkpoints into a temporary folder (0: none)",
    )
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--out", help="also write the JSON here")
    p.set_defaults(func=cmd_train)


def breakdown(exclusive: dict[str, float], total: float) -> dict[str, float]:
    """The PARTS' seconds from the timers' exclusive seconds, and `other`: the rest of
    `total` (the loop outside every section, and any section no part names)."""
    parts = {name: sum(exclusive.get(k, 0.0) for k in keys) for name, keys in PARTS.items()}
    parts["other"] = total - sum(parts.values())
    return {k: round(v, 4) for k, v in parts.items()}


def cmd_train(args: argparse.Namespace) -> int:
    for name in ("seeds", "steps"):
        if getattr(args, name) < 1:
            raise UsageError(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.test_interval < 0 or args.save_interval < 0:
        raise UsageError("--test-interval and --save-interval must be >= 0")
    overrides = [f"run.t_max={args.steps}", f"run.save_interval={args.save_interval}"]
    if args.test_interval:
        overrides.append(f"run.test_interval={args.test_interval}")
    cfg = load_train_config(args.algo, args.env, [], overrides + args.set)
    load_before = os.getloadavg()
    configure(cfg.run)
    with tempfile.TemporaryDirectory(prefix="credit-bench-train-") as tmp:
        trainer = LocalTrainer(
            cfg, n_ensemble=args.seeds, checkpoint_dir=Path(tmp) if args.save_interval else None
        )
        TIMERS.reset(enabled=True)
        try:
            started = time.perf_counter()
            trainer.train()
            total = time.perf_counter() - started
        finally:
            exclusive, counts = TIMERS.exclusive(), dict(TIMERS.counts)
            TIMERS.reset(enabled=False)
    parts = breakdown(exclusive, total)
    core = trainer.core
    updates = core.learner.updates
    emit(
        "train",
        {
            "env": args.env,
            "algo": args.algo,
            "seeds": args.seeds,
            "steps": args.steps,
            "overrides": args.set,
            "torch_threads": cfg.run.torch_threads,
            "precision": core.learning.precision,  # run.precision as this machine runs it
            "t_env": core.t_env,
            "env_steps_total": core.t_env * args.seeds,
            "total_s": round(total, 3),
            "env_steps_per_s": round(core.t_env / total, 2),
            "env_steps_per_s_all_seeds": round(core.t_env * args.seeds / total, 2),
            "updates": updates,
            "s_per_update": round(exclusive_update(exclusive) / updates, 4) if updates else None,
            "parts_s": parts,
            "parts_sum_s": round(sum(parts.values()), 3),
            "sections_exclusive_s": {k: round(v, 4) for k, v in sorted(exclusive.items())},
            "section_counts": dict(sorted(counts.items())),
            "load_avg_1m": {"before": load_before[0], "after": os.getloadavg()[0]},
        },
        args.out,
    )
    return 0


def exclusive_update(exclusive: dict[str, float]) -> float:
    """Seconds inside updates: the update section and everything nested in it."""
    return sum(s for k, s in exclusive.items() if k == "update" or k.startswith("update/"))
