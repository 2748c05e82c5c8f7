"""`credit inspect rdn-credit`: does RDN's LRP split credit each agent for its own action?

Trains RDN seed-batched on a map and, at every evaluation, measures on a replay batch how much
each agent's target moves with its own action against how much the critic's value moves
(`cluster.inspect.rdn_diagnostics.own_action_credit`), next to the greedy win rate: one JSON
line per evaluation, printed and appended to --out (results/smac/README.md, "Why the
dissertation's recipe collapses").

    credit inspect rdn-credit --env skirmish/3m --seeds 3 --t-max 60000 \\
        --out credit.jsonl [--set algo.td_lambda=0.8 ...]
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

from cluster.config.train import load_train_config
from cluster.inspect.rdn_diagnostics import own_action_credit
from cluster.launch.local import LocalTrainer
from cluster.process import configure


def run(
    env: str, seeds: int, t_max: int, sets: list[str], out: Path, emit: Callable[[str], None]
) -> int:
    """Train and measure; each evaluation's line goes to `emit` and is appended to `out`
    (emptied first). Returns the number of lines."""
    cfg = load_train_config("rdn", env, [], [f"run.t_max={t_max}", *sets])
    configure(cfg.run)
    trainer = LocalTrainer(cfg, n_ensemble=seeds)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("")
    lines = 0

    def on_eval(records) -> None:
        nonlocal lines
        line = {
            "t_env": records[0].t_env,
            "won": [r.test_won_mean for r in records],
            "updates": records[0].updates,
            "wall_s": round(records[0].wall_s, 1),
            "load_avg_1m": os.getloadavg()[0],
        }
        pair = trainer.data.sample()  # a replay batch, once the replay can serve one
        if pair is not None:
            line.update(own_action_credit(trainer.core.learner, pair[0]))
        text = json.dumps(line)
        emit(text)
        with open(out, "a") as f:
            f.write(text + "\n")
        lines += 1

    trainer.train(on_eval=on_eval)
    return lines
