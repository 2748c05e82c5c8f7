"""`credit bench matrix`: seed-batched training against the same seeds trained one by one.

Both arms run the same algorithm, game, seeds and env steps in this process, so the ratio is
a like-for-like measure of what batching seeds buys `credit repro matrix`.
"""

from __future__ import annotations

import argparse
import time

from cluster.bench.common import emit
from cluster.commands import add_command
from cluster.config.train import load_train_config
from cluster.launch.local import LocalTrainer
from cluster.process import configure


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "matrix",
        "Time seed-batched against one-by-one training on a matrix game and print JSON; "
        "--out also writes it.",
    )
    p.add_argument("--algo", default="rdn")
    p.add_argument("--env", default="matrix/four_game")
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--t-max", type=int, default=1000, help="env steps per seed")
    p.add_argument("--out", help="also write the JSON here")
    p.set_defaults(func=cmd_matrix)


def _time(algo: str, env: str, t_max: int, n_ensemble: int, seed: int) -> float:
    cfg = load_train_config(algo, env, [], [f"run.t_max={t_max}", f"run.seed={seed}"])
    configure(cfg.run)
    trainer = LocalTrainer(cfg, n_ensemble=n_ensemble)
    started = time.perf_counter()
    trainer.train()
    return time.perf_counter() - started


def cmd_matrix(args: argparse.Namespace) -> int:
    batched = _time(args.algo, args.env, args.t_max, args.seeds, 0)
    one_by_one = sum(_time(args.algo, args.env, args.t_max, 1, s) for s in range(args.seeds))
    steps = args.seeds * args.t_max
    emit(
        "matrix",
        {
            "algo": args.algo,
            "env": args.env,
            "seeds": args.seeds,
            "t_max_per_seed": args.t_max,
            "torch_threads": 1,
            "batched_s": round(batched, 3),
            "one_by_one_s": round(one_by_one, 3),
            "batched_env_steps_per_s": round(steps / batched, 1),
            "one_by_one_env_steps_per_s": round(steps / one_by_one, 1),
            "speedup": round(one_by_one / batched, 2),
        },
        args.out,
    )
    return 0
