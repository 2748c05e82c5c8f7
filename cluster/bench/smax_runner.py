"""Time JaxMARL's SMAX (heuristic enemy) on CPU; run as a script by `credit bench env --vs-smax`.

Standalone on purpose: it imports only jax and jaxmarl, so it can run under another Python
(`--smax-python PATH`, e.g. a venv with `pip install torch==2.13.0 jaxmarl`). It prints one
JSON object on the last line of stdout.

The timed loop mirrors a rollout actor: per step, one jitted+vmapped call that splits the
random keys, samples random valid actions, steps all envs (auto-reset) and returns the
observations (per agent, plus "world_state", SMAX's global state) and available actions;
`block_until_ready` closes each call. Compilation happens in warm-up steps, outside the timing.
"""

from __future__ import annotations

import argparse
import json
import os
import time


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--map", default="3m")
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--repeats", type=int, default=1, help="timed blocks of --steps steps")
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import jax
    import jax.numpy as jnp
    import jaxmarl
    from jaxmarl.environments.smax import HeuristicEnemySMAX, map_name_to_scenario

    env = HeuristicEnemySMAX(scenario=map_name_to_scenario(a.map))
    agents = env.agents

    def one(key, state):
        key, k_act, k_step = jax.random.split(key, 3)
        avail = env.get_avail_actions(state)
        keys = jax.random.split(k_act, len(agents))
        acts = {
            ag: jax.random.choice(k, avail[ag].shape[0], p=avail[ag] / avail[ag].sum())
            for k, ag in zip(keys, agents, strict=True)
        }
        obs, state, rew, _, _ = env.step(k_step, state, acts)
        avail = env.get_avail_actions(state)
        return key, state, obs, avail, rew

    # Keys are split inside the jitted call, so the timed loop is one dispatch per step.
    step = jax.jit(jax.vmap(one))
    keys = jax.random.split(jax.random.PRNGKey(a.seed), a.num_envs)
    _, state = jax.vmap(env.reset)(keys)
    for _ in range(a.warmup):
        keys, state, obs, avail, _ = step(keys, state)
    jax.block_until_ready((state, obs, avail))
    blocks = []
    for _ in range(max(a.repeats, 1)):
        t0 = time.perf_counter()
        for _ in range(a.steps):
            keys, state, obs, avail, _ = step(keys, state)
            jax.block_until_ready((obs, avail))
        blocks.append(time.perf_counter() - t0)
    best, median = min(blocks), sorted(blocks)[len(blocks) // 2]
    out = {
        "smax_env_steps_per_s": a.num_envs * a.steps / best,
        "smax_env_steps_per_s_median": a.num_envs * a.steps / median,
        "smax_agent_steps_per_s": a.num_envs * a.steps * len(agents) / best,
        "smax_block_seconds": blocks,
        "smax_map": a.map,
        "smax_num_envs": a.num_envs,
        "smax_steps": a.steps,
        "jax": jax.__version__,
        "jaxmarl": getattr(jaxmarl, "__version__", "unknown"),
        "jax_devices": [str(d) for d in jax.devices()],
        "jnp_float": str(jnp.zeros(1).dtype),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
