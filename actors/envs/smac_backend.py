"""`smac/<map>`: the real StarCraft II SMAC (oxwhirl) behind our env API, when installed.

SMAC is not a PyPI dependency: the package named `smac` on PyPI is SMAC3 (hyper-parameter
optimisation), a different project. Without oxwhirl's SMAC, building an env raises EnvError
with the install steps. `SmacEnv` only adapts: numpy arrays instead of lists, available-action
checks with our error message, `n_enemies`/`has_wins` in the env info, and
`info["episode_limit"]` set when the time limit (not the battle) ended the episode.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from actors.envs.base import EnvError, check_actions

SMAC_MAPS = ("3m", "8m", "2s3z", "3s5z", "1c3s5z", "MMM2", "2c_vs_64zg", "bane_vs_bane")
INSTALL_HELP = (
    "the real SMAC backend needs oxwhirl's SMAC and StarCraft II: "
    "`pip install git+https://github.com/oxwhirl/smac.git`, install StarCraft II "
    "(Linux package from Blizzard's s2client-proto releases) with the SMAC maps in "
    "$SC2PATH/Maps/SMAC_Maps, and set SC2PATH to the StarCraft II folder. Note: the PyPI "
    "package named `smac` is SMAC3, an unrelated hyper-parameter optimisation project. "
    "Without StarCraft II, use the built-in simulator `skirmish/<map>`."
)


def load_starcraft2env() -> Callable[..., Any]:
    """oxwhirl's `StarCraft2Env` class; EnvError with install steps when unavailable."""
    try:
        from smac.env import StarCraft2Env  # type: ignore[import-not-found]
    except ImportError as e:
        raise EnvError(f"cannot import smac.env.StarCraft2Env ({e}); {INSTALL_HELP}") from None
    if not all(hasattr(StarCraft2Env, m) for m in ("get_obs_agent", "get_avail_agent_actions")):
        raise EnvError(f"the installed `smac` is not oxwhirl's SMAC; {INSTALL_HELP}")
    return StarCraft2Env


class SmacEnv:
    """SMAC's StarCraft2Env adapted to our `MultiAgentEnv`.

    Args:
        map_name: SMAC map name.
        seed: SC2's random seed.
        env_cls: the class (or factory) to wrap; default oxwhirl's StarCraft2Env. Tests pass
            another SMAC-API implementation here.
        **kwargs: StarCraft2Env constructor options.
    """

    def __init__(
        self,
        map_name: str,
        seed: int | None = None,
        env_cls: Callable[..., Any] | None = None,
        **kwargs: Any,
    ):
        cls = env_cls if env_cls is not None else load_starcraft2env()
        self.env = cls(map_name=map_name, seed=seed, **kwargs)
        self.map_name = map_name
        info = self.env.get_env_info()
        self.n_agents = int(info["n_agents"])
        self.episode_limit = int(info["episode_limit"])
        self._t = 0

    def reset(self) -> tuple[np.ndarray, np.ndarray]:
        self._t = 0
        obs, state = self.env.reset()
        return np.asarray(obs, np.float32), np.asarray(state, np.float32)

    def step(self, actions) -> tuple[float, bool, dict[str, Any]]:
        acts = check_actions(actions, self.get_avail_actions())
        reward, terminated, info = self.env.step(acts.tolist())
        self._t += 1
        info = dict(info)
        won = bool(info.get("battle_won", False))
        cut = bool(terminated) and not won and self._t >= self.episode_limit
        info["battle_won"] = won
        info["episode_limit"] = bool(info.get("episode_limit", False)) or cut
        return float(reward), bool(terminated), info

    def get_obs(self) -> np.ndarray:
        return np.asarray(self.env.get_obs(), np.float32)

    def get_state(self) -> np.ndarray:
        return np.asarray(self.env.get_state(), np.float32)

    def get_avail_actions(self) -> np.ndarray:
        return np.asarray(self.env.get_avail_actions(), np.uint8)

    def get_env_info(self) -> dict[str, Any]:
        d = dict(self.env.get_env_info())
        d["n_enemies"] = int(self.env.n_enemies)
        d["has_wins"] = True
        return d

    def get_stats(self) -> dict[str, Any]:
        return dict(self.env.get_stats())

    def seed(self, seed: int | None = None) -> None:
        """SC2 takes its seed at launch; re-seeding needs a new env."""

    def close(self) -> None:
        self.env.close()


def make_smac_factory(map_name: str) -> Callable[..., SmacEnv]:
    def make(seed: int | None = None, **kwargs: Any) -> SmacEnv:
        return SmacEnv(map_name, seed=seed, **kwargs)

    return make
