"""Env steps per second of the real training loop, old commit against this one, side by side.

For every (env, algo) the variants run one after the other in separate processes, each with
PYTHONPATH at its own checkout and one torch thread: "old" times `LocalTrainer.train()` of
the old checkout for --steps env steps (it has no `credit bench train`), "new" and "new-bf16"
run `credit bench train` (which times the same call) with run.precision float32 / bf16.
Usage (from the repo root):

    python results/bench/train_old_new.py --old /tmp/speed_old \
        --out results/bench/train_old_new.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

OLD = """
import json, sys, time
from cluster.config.train import load_train_config
from cluster.launch.local import LocalTrainer
env, algo, seeds, steps = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
cfg = load_train_config(algo, env, [], [f"run.t_max={steps}", "run.save_interval=0"])
trainer = LocalTrainer(cfg, n_ensemble=seeds)
started = time.perf_counter()
trainer.train()
total = time.perf_counter() - started
t = trainer.core.t_env
print(json.dumps({"t_env": t, "total_s": round(total, 3), "env_steps_per_s": round(t / total, 2),
                  "updates": trainer.core.learner.updates}))
"""


def run(checkout: Path, args: list[str]) -> dict:
    env = {**os.environ, "PYTHONPATH": str(checkout), "OMP_NUM_THREADS": "1"}
    load = os.getloadavg()[0]
    out = subprocess.run(args, env=env, cwd=checkout, capture_output=True, text=True, check=True)
    rec = json.loads(out.stdout[out.stdout.index("{") :])
    keep = ("t_env", "total_s", "env_steps_per_s", "updates", "s_per_update", "parts_s")
    return {"load_avg_1m_before": load, **{k: rec[k] for k in keep if k in rec}}


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--old", required=True, help="a worktree of the old commit")
    p.add_argument("--runs", nargs="+", default=["skirmish/bane_vs_bane:3000", "skirmish/3m:6000"])
    p.add_argument("--algos", nargs="+", default=["rdn", "vdn", "qmix"])
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument(
        "--order", nargs="+", default=["old", "new", "new_bf16"], help="the variants' order"
    )
    p.add_argument("--out", required=True)
    a = p.parse_args()
    new, py = Path.cwd(), sys.executable
    rows = []
    for spec in a.runs:
        env, steps = spec.rsplit(":", 1)
        for algo in a.algos:
            common = [env, algo, str(a.seeds), steps]
            bench = [py, "-m", "cluster.cli", "bench", "train", "--env", env, "--algo", algo]
            bench += ["--seeds", str(a.seeds), "--steps", steps]
            row = {"env": env, "algo": algo, "seeds": a.seeds, "steps": int(steps)}
            variants = {
                "old": (Path(a.old), [py, "-c", OLD, *common]),
                "new": (new, bench),
                "new_bf16": (new, [*bench, "--set", "run.precision=bf16"]),
            }
            for name in a.order:
                row[name] = run(*variants[name])
            for v in ("new", "new_bf16"):
                if v not in row:
                    continue
                row[f"{v}_over_old"] = round(
                    row[v]["env_steps_per_s"] / row["old"]["env_steps_per_s"], 2
                )
            print(json.dumps(row), flush=True)
            rows.append(row)
    old_commit = subprocess.run(
        ["git", "-C", a.old, "rev-parse", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    new_commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True)
    record = {
        "command": " ".join(["python", *sys.argv]),
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "old_commit": old_commit,
        "new_commit": new_commit.stdout.strip(),
        "cpus": os.cpu_count(),
        "rows": rows,
    }
    Path(a.out).write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
