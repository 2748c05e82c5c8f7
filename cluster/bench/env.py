"""`credit bench env`: env-steps/s of a batched env under random valid actions, optionally
side by side with JaxMARL's SMAX.

    credit bench env --env skirmish/3m --num-envs 64 --steps 2000 [--repeats 3] [--vs-smax]
        [--smax-python /tmp/smaxvenv/bin/python] [--smax-map NAME] [--out results/bench/x.json]

Each timed step reads observations, state and available actions, samples a uniformly random
available action per agent and steps every env; finished envs are reset in place (the
rollout actor's loop). The loop runs `--repeats` blocks of `--steps` steps after a short
warm-up; `env_steps_per_s` is the best block (the least disturbed by other load on a shared
machine), `env_steps_per_s_median` the median. `--vs-smax` runs `cluster/bench/smax_runner.py`
(same map, number of envs, steps and repeats; JIT compile excluded; observations with
SMAX's world state and available actions every step, like ours) with `--smax-python`
(default: this Python, which then needs `jaxmarl`, the `smax` extra) on SMAX's map of the
same name, or for skirmish's SMACv2-style scenarios SMAX's randomised one of the same size
(`SMAX_PAIRS`: protoss/terran/zerg_5_vs_5 -> smacv2_5_units, ...; `--smax-map` overrides), and adds
`smax_env_steps_per_s` (best block), `smax_env_steps_per_s_median`, `ratio` (best / best)
and `ratio_median`.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from actors.envs.registry import make_vec_env
from cluster.bench.common import emit
from cluster.commands import add_command


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "env",
        "Measure env steps per second under random valid actions (optionally against "
        "JaxMARL SMAX) and print JSON; --out also writes it.",
    )
    p.add_argument("--env", default="skirmish/3m", help="registered env id")
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--steps", type=int, default=1000, help="vector steps per timed block")
    p.add_argument("--repeats", type=int, default=3, help="timed blocks (best and median kept)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--vs-smax", action="store_true", help="also time JaxMARL SMAX, same map")
    p.add_argument("--smax-python", default=sys.executable, help="python that has jaxmarl")
    p.add_argument("--smax-map", default=None, help="SMAX map (default: see smax_map_for)")
    p.add_argument("--out", default=None, help="also write the JSON here")
    p.set_defaults(func=cmd_env)


def time_env(env_id: str, num_envs: int, steps: int, seed: int = 0, repeats: int = 1) -> dict:
    """Run `repeats` blocks of `steps` vector steps of random valid actions (after a short
    warm-up that also compiles numba kernels); return throughput figures."""
    venv = make_vec_env(env_id, num_envs, seed=seed)
    rng = np.random.default_rng(seed)
    venv.reset()
    _run(venv, rng, min(steps, 20))
    blocks, episodes = [], 0
    for _ in range(max(repeats, 1)):
        t0 = time.perf_counter()
        episodes += _run(venv, rng, steps)
        blocks.append(time.perf_counter() - t0)
    n = venv.info.n_agents
    best, median = min(blocks), float(np.median(blocks))
    return {
        "env": env_id,
        "num_envs": num_envs,
        "steps": steps,
        "repeats": len(blocks),
        "block_seconds": blocks,
        "episodes": episodes,
        "env_steps_per_s": num_envs * steps / best,
        "env_steps_per_s_median": num_envs * steps / median,
        "agent_steps_per_s": num_envs * steps * n / best,
    }


def _run(venv, rng: np.random.Generator, steps: int) -> int:
    """`steps` rollout-actor steps (views, random valid actions, step, reset finished)."""
    active = np.ones(venv.num_envs, bool)
    episodes = 0
    for _ in range(steps):
        venv.get_obs()
        venv.get_state()
        avail = venv.get_avail_actions()
        actions = (avail * rng.random(avail.shape)).argmax(-1)
        _, terminated, _ = venv.step(actions, active)
        if terminated.any():
            episodes += int(terminated.sum())
            _reset_done(venv, terminated)
    return episodes


def _reset_done(venv, done: np.ndarray) -> None:
    """Reset only the finished envs where the VecEnv supports it, else all of them."""
    reset_some = getattr(venv, "reset_envs", None)
    if reset_some is not None:
        reset_some(np.flatnonzero(done))
    else:
        venv.reset()


# skirmish's SMACv2-style scenarios -> SMAX's randomised scenarios of the same team sizes
# (SMAX draws unit types from all of its six types and random start positions).
SMAX_PAIRS = {
    f"{race}_{n}_vs_{n}": f"smacv2_{n}_units"
    for race in ("protoss", "terran", "zerg")
    for n in (5, 10, 20)
}


def smax_map_for(env_id: str) -> str:
    """SMAX's map to compare `env_id` with: its SMACv2 pair, else the same map name."""
    name = env_id.split("/", 1)[1]
    return SMAX_PAIRS.get(name, name)


def time_smax(python: str, map_name: str, num_envs: int, steps: int, repeats: int = 1) -> dict:
    runner = Path(__file__).with_name("smax_runner.py")
    cmd = [python, str(runner), "--map", map_name, "--num-envs", str(num_envs)]
    cmd += ["--steps", str(steps), "--repeats", str(repeats)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"SMAX runner failed ({' '.join(cmd)}):\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def cmd_env(args: argparse.Namespace) -> int:
    figures = time_env(args.env, args.num_envs, args.steps, args.seed, args.repeats)
    if args.vs_smax:
        map_name = args.smax_map or smax_map_for(args.env)
        smax = time_smax(args.smax_python, map_name, args.num_envs, args.steps, args.repeats)
        figures.update(smax)
        figures["ratio"] = figures["env_steps_per_s"] / smax["smax_env_steps_per_s"]
        figures["ratio_median"] = (
            figures["env_steps_per_s_median"] / smax["smax_env_steps_per_s_median"]
        )
    emit("env", figures, args.out)
    return 0
