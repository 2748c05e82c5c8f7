"""Does RDN's LRP split credit each agent for its own action? Trains RDN seed-batched on a
skirmish map and, at every evaluation, measures on a replay batch how much each agent's target
moves with its own action against how much the critic's value moves
(`cluster.inspect.rdn_diagnostics.own_action_credit`), next to the greedy win rate. One JSON
line per evaluation on stdout, and the same lines in --out.

    python -m cluster.bench.rdn_credit --env skirmish/3m --seeds 3 --t-max 60000 \
        --out credit.jsonl [--set algo.lrp_rule=eps ...]
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import torch

from cluster.config.train import load_train_config
from cluster.inspect.rdn_diagnostics import own_action_credit
from cluster.launch.local import LocalTrainer


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="skirmish/3m")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--t-max", type=int, default=60_000)
    p.add_argument("--out", required=True)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args()
    torch.set_num_threads(1)
    cfg = load_train_config("rdn", args.env, [], [f"run.t_max={args.t_max}", *args.set])
    trainer = LocalTrainer(cfg, n_ensemble=args.seeds)
    out = Path(args.out)
    out.write_text("")

    def on_eval(records) -> None:
        plan = trainer.core.plan
        line = {
            "t_env": records[0].t_env,
            "won": [r.test_won_mean for r in records],
            "updates": records[0].updates,
            "wall_s": round(records[0].wall_s, 1),
            "load_avg_1m": os.getloadavg()[0],
        }
        if all(b.ready(plan.table, plan.batch_size) for b in trainer.data.buffers):
            batch, _ = trainer.data.sample()
            line.update(own_action_credit(trainer.core.learner, batch))
        text = json.dumps(line)
        print(text, flush=True)
        with open(out, "a") as f:
            f.write(text + "\n")

    trainer.train(on_eval=on_eval)


if __name__ == "__main__":
    main()
