"""`credit bench memory`: what one stored env step costs, and a short training run's peak RSS.

Records `--episodes` episodes per seed with the run's own acting network at the start of
its exploration schedule (epsilon 1 on the shipped configs: a random policy), then reports,
as JSON:

* bytes per stored env step and per agent-step in the old layout (`Episode`'s seven dense
  arrays, what the buffer stored before issue 35) and the new (`PackedEpisode`, with the
  state only when the algorithm reads it, `AlgoSpec.reads_state`), and their ratio;
* the cost of making one learner batch from stored episodes (decoding them) against making
  it from dense ones, and against one learner update on that batch (median of `--repeats`);
* the peak RSS (VmHWM) of a short local training run (`--steps` env steps, `--seeds` seeds)
  in a fresh process, with its stored replay bytes at the end and the rest (the overhead:
  interpreter, torch, envs, networks, the update's working set).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from typing import Any

from actors.envs.registry import make_vec_env
from actors.rollout import RolloutWorker
from buffer_service.episode import Episode, EpisodeBatch
from buffer_service.packed import PackedEpisode, dense_bytes
from cluster.bench.common import emit
from cluster.commands import add_command
from cluster.config.train import load_train_config
from learner.registry import get_algo

# The training run of the RSS figure, in a fresh process (argv: env, algo, seeds, steps).
CHILD = """
import json, sys, time
from cluster.config.train import load_train_config
from cluster.launch.local import LocalTrainer
from cluster.process import configure
env, algo, seeds, steps = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
cfg = load_train_config(algo, env, [], [f"run.t_max={steps}", f"run.test_interval={10 * steps}"])
started = time.perf_counter()
configure(cfg.run)
trainer = LocalTrainer(cfg, n_ensemble=seeds)
trainer.train()
stored = sum(b.stats()["episode_bytes"] for b in trainer.data.buffers)
status = {k: int(v.split()[0]) * 1024 for k, v in
          (line.split(":", 1) for line in open("/proc/self/status")) if k in ("VmHWM", "VmRSS")}
print(json.dumps({"t_env": trainer.core.t_env, "episodes": trainer.core.episodes,
                  "updates": trainer.stats.updates, "stored_bytes": stored,
                  "peak_rss_bytes": status["VmHWM"], "end_rss_bytes": status["VmRSS"],
                  "wall_s": round(time.perf_counter() - started, 1)}))
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "memory",
        "Bytes per stored env step and agent-step in the old and the new (packed) layout, "
        "the cost of decoding a batch, and a short training run's peak RSS, as JSON; --out "
        "also writes it.",
    )
    p.add_argument("--env", default="skirmish/bane_vs_bane")
    p.add_argument("--algo", default="rdn")
    p.add_argument("--episodes", type=int, default=32, help="recorded episodes per seed")
    p.add_argument("--seeds", type=int, default=3, help="ensemble members (batch and run)")
    p.add_argument("--repeats", type=int, default=3, help="timings: median of this many")
    p.add_argument("--steps", type=int, default=2000, help="env steps of the training run")
    p.add_argument("--out", help="also write the JSON here")
    p.set_defaults(func=cmd_memory)


def record(env: str, algo: str, episodes: int, seeds: int) -> tuple[Any, list[list[Episode]]]:
    """(config, `episodes` episodes per seed) acted by the run's network at t_env = 0."""
    cfg = load_train_config(algo, env, [], [])
    venv = make_vec_env(env, episodes * seeds, seed=0, **cfg.env.args)
    spec = get_algo(algo)
    learner = spec.build(cfg.algo, venv.info.schema(), seeds, "cpu")
    worker = RolloutWorker(venv, learner.agent, learner.policy_kind, cfg.exploration, seeds)
    eps = worker.run_round(t_env=0).episodes
    return cfg, [eps[k * episodes : (k + 1) * episodes] for k in range(seeds)]


def layout_figures(episodes: list[Episode], state: bool) -> dict[str, Any]:
    """Bytes per stored env step and agent-step, old and new layout."""
    steps = sum(ep.length for ep in episodes)
    agents = episodes[0].obs.shape[1]
    old = sum(dense_bytes(ep) for ep in episodes)
    new = sum(PackedEpisode.pack(ep, state).nbytes for ep in episodes)
    with_state = sum(PackedEpisode.pack(ep, True).nbytes for ep in episodes)
    return {
        "episodes": len(episodes),
        "mean_length": round(steps / len(episodes), 1),
        "old_bytes_per_env_step": round(old / steps),
        "old_bytes_per_agent_step": round(old / steps / agents),
        "new_bytes_per_env_step": round(new / steps),
        "new_bytes_per_agent_step": round(new / steps / agents),
        "new_stores_state": state,
        "new_with_state_bytes_per_env_step": round(with_state / steps),
        "old_over_new": round(old / new, 2),
    }


def _median_s(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def decode_figures(cfg, members: list[list[Episode]], state: bool, repeats: int) -> dict:
    """Making one learner batch from packed against dense episodes, and one update."""
    batch = cfg.replay.batch_size
    dense = [m[:batch] for m in members]
    packed = [[PackedEpisode.pack(ep, state) for ep in m] for m in dense]
    made = EpisodeBatch.from_members(packed)
    assert all(  # the exact encoding: the batch is the same, bit for bit
        getattr(made, k).tobytes() == getattr(EpisodeBatch.from_members(dense), k).tobytes()
        for k in ("obs", "avail_actions", "actions", "reward", "terminated", "filled")
    )
    schema = make_vec_env(cfg.env.id, 1, seed=0, **cfg.env.args).info.schema()
    learner = get_algo(cfg.algo_name).build(cfg.algo, schema, len(members), "cpu")
    learner.step(made)  # warm-up
    dense_s = _median_s(lambda: EpisodeBatch.from_members(dense), repeats)
    packed_s = _median_s(lambda: EpisodeBatch.from_members(packed), repeats)
    update_s = _median_s(lambda: learner.step(made), repeats)
    return {
        "batch_episodes_per_seed": len(dense[0]),
        "batch_from_dense_ms": round(dense_s * 1e3, 1),
        "batch_from_packed_ms": round(packed_s * 1e3, 1),
        "update_ms": round(update_s * 1e3, 1),
        "decode_over_update": round(packed_s / update_s, 3),
        "bit_identical": True,
    }


def train_figures(env: str, algo: str, seeds: int, steps: int) -> dict[str, Any]:
    out = (
        subprocess.run(
            [sys.executable, "-c", CHILD, env, algo, str(seeds), str(steps)],
            capture_output=True,
            text=True,
            check=True,
        )
        .stdout.strip()
        .splitlines()[-1]
    )
    run = json.loads(out)
    run["peak_rss_mib"] = round(run["peak_rss_bytes"] / 2**20)
    run["stored_mib"] = round(run["stored_bytes"] / 2**20, 1)
    run["peak_rss_minus_stored_mib"] = round((run["peak_rss_bytes"] - run["stored_bytes"]) / 2**20)
    return {"seeds": seeds, "steps": steps, **run}


def _load() -> float:
    with open("/proc/loadavg") as f:
        return float(f.read().split()[0])


def cmd_memory(args: argparse.Namespace) -> int:
    load_before = _load()
    cfg, members = record(args.env, args.algo, args.episodes, args.seeds)
    state = get_algo(args.algo).reads_state(cfg.algo)
    figures: dict[str, Any] = {
        "env": args.env,
        "algo": args.algo,
        "episodes_from": "the run's network at t_env 0 (its exploration's start), env seed 0",
        "layout": layout_figures([ep for m in members for ep in m], state),
        "decode": decode_figures(cfg, members, state, args.repeats),
    }
    if args.steps > 0:
        figures["training"] = train_figures(args.env, args.algo, args.seeds, args.steps)
    figures["load_avg_1m"] = [load_before, _load()]
    emit("memory", figures, args.out)
    return 0
