"""The environment interfaces: SMAC's `MultiAgentEnv` and a batched `VecEnv`.

A SMAC user drops any of our envs into a pymarl-style loop::

    env = make_env("matrix/two_step", seed=0)
    info = env.get_env_info()
    obs, state = env.reset()
    terminated = False
    while not terminated:
        avail = env.get_avail_actions()          # [N, A]
        actions = policy(env.get_obs(), avail)    # [N] ints, each available
        reward, terminated, step_info = env.step(actions)
    # step_info["battle_won"] where the env has wins; step_info["episode_limit"] is True
    # when the time limit (not the game) ended the episode: bootstrap, do not treat as terminal.

`VecEnv` steps M environments in one call; a rollout worker owns one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from buffer_service.episode import EpisodeSchema


class EnvError(ValueError):
    """Bad env id, bad env arguments, or an action the env cannot take."""


@dataclass(frozen=True)
class EnvInfo:
    """Static sizes of an environment (SMAC's get_env_info() as a typed record)."""

    n_agents: int
    n_actions: int
    obs_shape: int
    state_shape: int
    episode_limit: int
    has_wins: bool = True
    n_enemies: int = 0

    def schema(self) -> EpisodeSchema:
        """The episode schema every episode of this env satisfies."""
        return EpisodeSchema(
            self.n_agents, self.obs_shape, self.state_shape, self.n_actions, self.episode_limit
        )

    def as_smac_dict(self) -> dict[str, int]:
        return {
            "state_shape": self.state_shape,
            "obs_shape": self.obs_shape,
            "n_actions": self.n_actions,
            "n_agents": self.n_agents,
            "episode_limit": self.episode_limit,
        }


class MultiAgentEnv(Protocol):
    """SMAC's environment API (see the module docstring for the calling loop)."""

    def reset(self) -> tuple[np.ndarray, np.ndarray]: ...
    def step(self, actions: np.ndarray) -> tuple[float, bool, dict[str, Any]]: ...
    def get_obs(self) -> np.ndarray: ...
    def get_state(self) -> np.ndarray: ...
    def get_avail_actions(self) -> np.ndarray: ...
    def get_env_info(self) -> dict[str, int]: ...
    def get_stats(self) -> dict[str, Any]: ...
    def seed(self, seed: int | None = None) -> None: ...
    def close(self) -> None: ...


class VecEnv(Protocol):
    """M environments stepped together; the calling loop::

        venv.reset()
        active = np.ones(venv.num_envs, bool)
        while active.any():
            obs, avail = venv.get_obs(), venv.get_avail_actions()  # [M, N, O], [M, N, A]
            reward, terminated, infos = venv.step(actions, active)  # [M], [M], list of M dicts
            active &= ~terminated
    As in SMAC, `terminated` is also True when the time limit cut the episode; that env's info
    then has episode_limit=True.
    Inactive envs are not stepped: their reward is 0, terminated True and info empty.
    """

    num_envs: int
    info: EnvInfo

    def reset(self) -> None: ...
    def step(
        self, actions: np.ndarray, active: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, list[dict]]: ...
    def get_obs(self) -> np.ndarray: ...
    def get_state(self) -> np.ndarray: ...
    def get_avail_actions(self) -> np.ndarray: ...
    def close(self) -> None: ...


def env_info_of(env: MultiAgentEnv) -> EnvInfo:
    """Typed EnvInfo from an env's SMAC-style dict (extra keys allowed)."""
    d = env.get_env_info()
    return EnvInfo(
        n_agents=int(d["n_agents"]),
        n_actions=int(d["n_actions"]),
        obs_shape=int(d["obs_shape"]),
        state_shape=int(d["state_shape"]),
        episode_limit=int(d["episode_limit"]),
        has_wins=bool(d.get("has_wins", True)),
        n_enemies=int(d.get("n_enemies", 0)),
    )


def check_actions(actions: np.ndarray, avail: np.ndarray) -> np.ndarray:
    """Return `actions` as int64 [N]; raise EnvError naming the agent and action if unavailable."""
    acts = np.asarray(actions, dtype=np.int64).reshape(-1)
    if acts.shape[0] != avail.shape[0]:
        raise EnvError(f"expected {avail.shape[0]} actions (one per agent), got {acts.shape[0]}")
    for i, a in enumerate(acts):
        if not 0 <= a < avail.shape[1] or not avail[i, a]:
            valid = np.flatnonzero(avail[i]).tolist()
            raise EnvError(f"agent {i} cannot take action {int(a)} now; available: {valid}")
    return acts


class SerialVecEnv:
    """VecEnv over a list of single `MultiAgentEnv`s, stepped one after another."""

    def __init__(self, envs: list[MultiAgentEnv]):
        if not envs:
            raise EnvError("SerialVecEnv needs at least one env")
        self.envs = envs
        self.num_envs = len(envs)
        self.info = env_info_of(envs[0])

    def reset(self) -> None:
        for env in self.envs:
            env.reset()

    def step(
        self, actions: np.ndarray, active: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, list[dict]]:
        reward = np.zeros(self.num_envs, np.float32)
        terminated = np.ones(self.num_envs, bool)
        infos: list[dict] = [{} for _ in range(self.num_envs)]
        for k, env in enumerate(self.envs):
            if active[k]:
                r, term, infos[k] = env.step(actions[k])
                reward[k], terminated[k] = r, term
        return reward, terminated, infos

    def get_obs(self) -> np.ndarray:
        return np.stack([np.asarray(e.get_obs(), np.float32) for e in self.envs])

    def get_state(self) -> np.ndarray:
        return np.stack([np.asarray(e.get_state(), np.float32) for e in self.envs])

    def get_avail_actions(self) -> np.ndarray:
        return np.stack([np.asarray(e.get_avail_actions(), np.uint8) for e in self.envs])

    def get_rng_state(self) -> list[Any]:
        """Each env's generator state, None for an env that cannot give one."""
        return [rng_state(env) for env in self.envs]

    def set_rng_state(self, state: list[Any]) -> None:
        for env, s in zip(self.envs, state, strict=True):
            set_rng_state(env, s)

    def close(self) -> None:
        for env in self.envs:
            env.close()


def rng_state(env: Any) -> Any:
    """The random state of an env or VecEnv that offers one (`get_rng_state`), else None.

    A checkpoint keeps it so that a resumed run draws the episodes an uninterrupted run would
    have drawn (skirmish and matrix games: exactly; an env without `get_rng_state`, such as
    real SMAC, continues from a fresh state)."""
    get = getattr(env, "get_rng_state", None)
    return get() if get is not None else None


def set_rng_state(env: Any, state: Any) -> None:
    """Restore what `rng_state` returned (nothing to do for None)."""
    if state is not None:
        env.set_rng_state(state)
