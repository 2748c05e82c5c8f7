"""PettingZoo `ParallelEnv` over any registered env (skirmish maps, matrix games, ...).

    env = parallel_env("skirmish/3m", seed=0)
    obs, infos = env.reset(seed=0)
    while env.agents:
        actions = {a: env.action_space(a).sample(mask=obs[a]["action_mask"]) for a in env.agents}
        obs, rewards, terminations, truncations, infos = env.step(actions)

Observations are dicts {"observation": float32 [obs_dim], "action_mask": int8 [n_actions]}.
Every agent stays in `agents` until the episode ends (dead SMAC units can only take the
no-op, as the mask says); the shared team reward goes to every agent. A time-limit cut is a
truncation, a decided battle a termination. `state()` returns the global state.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from actors.envs.base import EnvError, env_info_of
from actors.envs.registry import make_env

try:
    from gymnasium import spaces
    from pettingzoo import ParallelEnv
except ImportError as e:  # pragma: no cover - exercised only without the extra
    raise ImportError("actors.envs.pettingzoo needs `pip install credit[pettingzoo]`") from e


class SmacParallelEnv(ParallelEnv):
    """ParallelEnv around one SMAC-API env built from the registry.

    Args:
        env_id: registered id, e.g. "skirmish/3m" or "matrix/two_step".
        seed: passed to the env; `reset(seed=...)` re-seeds.
        **kwargs: env arguments (see `credit env list`).
    """

    metadata: ClassVar[dict] = {"name": "credit_smac_parallel", "render_modes": []}

    def __init__(self, env_id: str, seed: int | None = None, **kwargs: Any):
        self.env_id = env_id
        self._kwargs = kwargs
        self.env = make_env(env_id, seed=seed, **kwargs)
        self.info = env_info_of(self.env)
        self.possible_agents = [f"agent_{i}" for i in range(self.info.n_agents)]
        self.agents: list[str] = []
        self.render_mode = None
        self.state_space = spaces.Box(-np.inf, np.inf, (self.info.state_shape,), np.float32)
        self._obs_space = spaces.Dict(
            {
                "observation": spaces.Box(-np.inf, np.inf, (self.info.obs_shape,), np.float32),
                "action_mask": spaces.Box(0, 1, (self.info.n_actions,), np.int8),
            }
        )
        self._act_space = spaces.Discrete(self.info.n_actions)

    def observation_space(self, agent: str) -> spaces.Dict:
        """The same space object for every agent (PettingZoo checks identity)."""
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Discrete:
        return self._act_space

    def _observe(self) -> dict[str, dict[str, np.ndarray]]:
        obs = np.asarray(self.env.get_obs(), np.float32)
        mask = np.asarray(self.env.get_avail_actions(), np.int8)
        return {
            a: {"observation": obs[i], "action_mask": mask[i]}
            for i, a in enumerate(self.possible_agents)
        }

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Start an episode; returns (observations, infos) keyed by agent."""
        if seed is not None:
            self.env.seed(seed)
        self.env.reset()
        self.agents = list(self.possible_agents)
        return self._observe(), {a: {} for a in self.agents}

    def step(self, actions: dict[str, int]):
        """Apply every live agent's action; returns obs, rewards, terminations,
        truncations, infos (dicts keyed by agent)."""
        if not self.agents:
            raise EnvError("step() after the episode ended; call reset()")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise EnvError(f"no action for {missing}")
        acts = np.array([int(actions[a]) for a in self.possible_agents], np.int64)
        reward, terminated, info = self.env.step(acts)
        cut = bool(info.get("episode_limit", False))
        obs = self._observe()
        agents = self.agents
        rewards = dict.fromkeys(agents, float(reward))
        terms = dict.fromkeys(agents, bool(terminated) and not cut)
        truncs = dict.fromkeys(agents, cut)
        infos = {a: dict(info) for a in agents}
        if terminated:
            self.agents = []
        return obs, rewards, terms, truncs, infos

    def state(self) -> np.ndarray:
        return np.asarray(self.env.get_state(), np.float32)

    def close(self) -> None:
        self.env.close()


def parallel_env(env_id: str, **kwargs: Any) -> SmacParallelEnv:
    """A PettingZoo ParallelEnv for a registered env id (kwargs go to the env)."""
    return SmacParallelEnv(env_id, **kwargs)
