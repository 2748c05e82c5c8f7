"""How large the policy-gradient term is against the entropy bonus, per map.

Trains CAC (3 seeds batched, the shipped config with the raw advantages: advantage_norm off)
for --t-max env steps on each map and records, for every update, the mean |advantage| over
real (step, agent) entries and the policy entropy.
The policy loss is -mean(log pi(u) A + beta H): where mean |A| is small next to beta, the
entropy bonus dominates and the policy drifts towards uniform.

    python -m cluster.bench.advantage_scale --maps 3m,2s3z,3s5z --t-max 30000 \
        --out results/pg/why/advantage_scale.json
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from cluster.config.train import load_train_config
from cluster.launch.local import LocalTrainer


def measure(env: str, algo: str, t_max: int, beta: float | None) -> dict:
    overrides = [f"run.t_max={t_max}", "run.test_interval=100000000"]
    if hasattr(load_train_config(algo, env).algo, "advantage_norm"):  # the CAC family
        # The raw scale is what is measured: normalised advantages have unit spread.
        overrides.append("algo.advantage_norm=false")
    if beta is not None:
        overrides.append(f"algo.entropy_coef={beta}")
    cfg = load_train_config(algo, env, [], overrides)
    trainer = LocalTrainer(cfg, n_ensemble=3)
    adv, ent, lengths = [], [], []
    learner = trainer.core.learner
    step = learner.step

    def recording_step(batch, extra=None):
        metrics = step(batch, extra)
        adv.append(metrics["advantage_abs_mean"])
        ent.append(metrics["entropy"])
        lengths.append(float(batch.filled.sum(-1).mean()))
        return metrics

    learner.step = recording_step
    trainer.train()
    half = len(adv) // 2  # the second half: past the first random-policy episodes
    return {
        "env": env,
        "algo": algo,
        "entropy_coef": cfg.algo.entropy_coef,
        "t_env": trainer.core.t_env,
        "updates": len(adv),
        "advantage_abs_mean": float(np.mean(adv[half:])),
        "entropy_mean": float(np.mean(ent[half:])),
        "episode_length_mean": float(np.mean(lengths[half:])),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--maps", default="3m,2s3z,3s5z")
    p.add_argument("--algo", default="cac")
    p.add_argument("--t-max", type=int, default=30000)
    p.add_argument("--beta", type=float, default=None, help="entropy_coef (default: shipped)")
    p.add_argument("--out")
    args = p.parse_args()
    torch.set_num_threads(1)
    maps = args.maps.split(",")
    rows = [measure(f"skirmish/{m}", args.algo, args.t_max, args.beta) for m in maps]
    for r in rows:
        r["advantage_over_beta"] = r["advantage_abs_mean"] / r["entropy_coef"]
    text = json.dumps({"command_args": vars(args), "rows": rows}, indent=2)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
