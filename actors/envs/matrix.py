"""Two-step cooperative matrix games (QMIX paper's two-step game and the dissertation's four-game).

Both have two agents with two actions. Step 1 pays 0 and the agents' actions pick a payoff
matrix; step 2 pays that matrix's entry [action of agent 0, action of agent 1] and ends the
episode. Observation and state are the one-hot of the current stage, the same for both
agents, so the agents see which matrix they are in but not each other's action.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from actors.envs.base import EnvError, check_actions

# Payoff matrices indexed [row = agent 0's action][column = agent 1's action].
TWO_STEP_GAMES: tuple[tuple[tuple[float, ...], ...], ...] = (
    ((7.0, 7.0), (7.0, 7.0)),  # 2A: chosen when agent 0 plays 0 at step 1
    ((0.0, 1.0), (1.0, 8.0)),  # 2B: chosen when agent 0 plays 1
)
FOUR_GAMES: dict[str, tuple[tuple[float, ...], ...]] = {
    "00": ((7.0, 7.0), (7.0, 7.0)),
    "01": ((2.0, 0.0), (0.0, 2.0)),
    "11": ((0.0, 1.0), (1.0, 8.0)),
    "10": ((2.0, 2.0), (2.0, 2.0)),
}


@dataclass(frozen=True)
class MatrixGameConfig:
    """Payoffs of the four-game (keys "<row><col>" of the step-1 joint action).

    Attributes:
        payoffs: the 2x2 payoff matrix of the game picked by each step-1 joint action.
    """

    payoffs: dict[str, tuple[tuple[float, ...], ...]] = field(
        default_factory=lambda: dict(FOUR_GAMES)
    )

    def validate(self) -> None:
        if set(self.payoffs) != set(FOUR_GAMES):
            raise EnvError(
                f"env.payoffs needs exactly the keys {sorted(FOUR_GAMES)}, "
                f"got {sorted(self.payoffs)}"
            )
        for key, m in self.payoffs.items():
            arr = np.asarray(m, dtype=np.float64)
            if arr.shape != (2, 2) or not np.all(np.isfinite(arr)):
                raise EnvError(f"env.payoffs[{key!r}] must be a finite 2x2 matrix, got {m!r}")


class MatrixGame:
    """Shared mechanics: a start stage, then one of `len(games)` payoff stages."""

    n_agents = 2
    n_actions = 2
    episode_limit = 2

    def __init__(self, games: list[np.ndarray], pick_game, seed: int | None = None):
        self._games = games
        self._pick = pick_game
        self._n_stages = 1 + len(games)
        self._stage = 0
        self._t = 0
        self._done = False
        self._return = 0.0
        self._episodes = 0

    # -- SMAC API ---------------------------------------------------------------------------
    def reset(self) -> tuple[np.ndarray, np.ndarray]:
        self._stage, self._t, self._done, self._return = 0, 0, False, 0.0
        return self.get_obs(), self.get_state()

    def step(self, actions) -> tuple[float, bool, dict[str, Any]]:
        if self._done:
            raise EnvError("step() called on a finished episode; call reset() first")
        a = check_actions(actions, self.get_avail_actions())
        if self._t == 0:
            self._stage = 1 + self._pick(int(a[0]), int(a[1]))
            reward, self._done = 0.0, False
        else:
            reward = float(self._games[self._stage - 1][a[0], a[1]])
            self._done = True
            self._episodes += 1
        self._t += 1
        self._return += reward
        return reward, self._done, {"episode_limit": False}

    def get_obs(self) -> np.ndarray:
        return np.repeat(self.get_state()[None], self.n_agents, axis=0)

    def get_obs_agent(self, agent_id: int) -> np.ndarray:
        return self.get_state()

    def get_state(self) -> np.ndarray:
        s = np.zeros(self._n_stages, np.float32)
        s[self._stage] = 1.0
        return s

    def get_avail_actions(self) -> np.ndarray:
        return np.ones((self.n_agents, self.n_actions), np.uint8)

    def get_env_info(self) -> dict[str, Any]:
        return {
            "state_shape": self._n_stages,
            "obs_shape": self._n_stages,
            "n_actions": self.n_actions,
            "n_agents": self.n_agents,
            "episode_limit": self.episode_limit,
            "has_wins": False,
            "n_enemies": 0,
        }

    def get_stats(self) -> dict[str, Any]:
        return {"episodes": self._episodes, "last_return": self._return}

    def seed(self, seed: int | None = None) -> None:
        """The games are deterministic; seeding is accepted for API compatibility."""

    def close(self) -> None:
        pass

    @property
    def optimal_return(self) -> float:
        return max(float(g.max()) for g in self._games)


def make_two_step(seed: int | None = None) -> MatrixGame:
    """QMIX paper's two-step game: agent 0's step-1 action alone picks 2A or 2B. Optimum 8."""
    games = [np.asarray(g, np.float32) for g in TWO_STEP_GAMES]
    return MatrixGame(games, lambda a0, a1: a0, seed)


def make_four_game(seed: int | None = None, payoffs: dict | None = None) -> MatrixGame:
    """Seed Fig. 5.1: agent 0's row and agent 1's column pick one of four games."""
    cfg = MatrixGameConfig() if payoffs is None else MatrixGameConfig(payoffs=payoffs)
    cfg.validate()
    keys = ["00", "01", "10", "11"]
    games = [np.asarray(cfg.payoffs[k], np.float32) for k in keys]
    return MatrixGame(games, lambda a0, a1: keys.index(f"{a0}{a1}"), seed)
