"""What share of an update's agent-rows are living agents, in batches of a trained policy.

python results/bench/rows_2026-12-06/rows.py CHECKPOINT_DIR [EPISODES]

Plays EPISODES (default 32) greedy episodes of member 0 of a trained checkpoint (as `credit
inspect relevance` does) and prints one JSON line: the win rate, episode lengths, and the
share of agent-rows that are a living agent's real step, (a) of the batch padded to its longest
episode and (b) of the rows that the update's passes (`learner.passes`, the default
`update_pass_rows`, 3 seed-batched members of the same episodes) compute.
"""

import json
import sys
from pathlib import Path

import numpy as np
import torch

from cluster.inspect.relevance import load_member, play
from learner.passes import UPDATE_PASS_ROWS, pass_plan

ckpt = Path(sys.argv[1])
n_eps = int(sys.argv[2]) if len(sys.argv) > 2 else 32
cfg, learner = load_member(ckpt, 0)
eps, won, _ = play(cfg, learner, n_eps, seed=7)
lengths = np.array([e.length for e in eps])
n = eps[0].actions.shape[1]
# a dead agent has only no-op (action 0) available
alive = sum(int(e.avail_actions[:-1, :, 1:].any(-1).sum()) for e in eps)
members = 3
srt = torch.tensor(np.sort(lengths)).view(1, -1).expand(members, -1)
plan = pass_plan(srt, n, UPDATE_PASS_ROWS)
pass_rows = sum((hi - lo) * (int(srt[0, hi - 1]) + 1) * n for lo, hi in plan)
padded_rows = len(lengths) * (int(lengths.max()) + 1) * n
print(
    json.dumps(
        {
            "checkpoint": str(ckpt),
            "env": cfg.env.id,
            "algo": cfg.algo_name,
            "episodes": len(eps),
            "win_rate": float(np.mean(won)),
            "length_mean": float(lengths.mean()),
            "length_max": int(lengths.max()),
            "agents": n,
            "passes": len(plan),
            "living_of_real_agent_steps": round(alive / (lengths.sum() * n), 3),
            "living_of_padded_batch_rows": round(alive / padded_rows, 3),
            "living_of_pass_rows": round(alive / pass_rows, 3),
            "real_of_pass_rows": round(float(lengths.sum() * n / pass_rows), 3),
        }
    )
)
