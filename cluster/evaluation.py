"""Greedy evaluation (`Evaluator`): every member's test episodes on envs of their own, and
the records they give (`EvalRecord`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from actors.envs.base import VecEnv, rng_state, set_rng_state
from actors.envs.registry import make_vec_env
from cluster.config.train import TrainConfig
from cluster.context import RunContext
from cluster.learning import Learning


@dataclass(frozen=True)
class EvalRecord:
    """One greedy evaluation of one ensemble member."""

    member: int
    t_env: int
    episode: int
    test_return_mean: float
    test_won_mean: float | None
    wall_s: float
    updates: int

    def as_json(self) -> dict:
        d = {
            "t_env": self.t_env,
            "episode": self.episode,
            "test_return_mean": self.test_return_mean,
            "wall_s": round(self.wall_s, 3),
            "updates": self.updates,
        }
        if self.test_won_mean is not None:
            d["test_won_mean"] = self.test_won_mean
        return d


def make_test_envs(cfg: TrainConfig, n_ensemble: int) -> VecEnv:
    """run.test_episodes envs per member, seeded apart from the training envs."""
    run = cfg.run
    return make_vec_env(
        cfg.env.id, n_ensemble * run.test_episodes, seed=run.seed + 10_000, **cfg.env.args
    )


class Evaluator:
    """Plays run.test_episodes greedy episodes per member with the learner's current weights.

    Args:
        ctx: the run.
        learning: the learner the test worker follows.
        venv: the test envs (`make_test_envs`).
    """

    def __init__(self, ctx: RunContext, learning: Learning, venv: VecEnv) -> None:
        self.ctx, self.learning, self.venv = ctx, learning, venv
        self.worker = learning.local_worker(venv, ctx.run.seed + 1)

    def evaluate(self, t_env: int, episodes: int, wall_s: float) -> list[EvalRecord]:
        """Greedy episodes for every member at the loop's `t_env` and `episodes`; one record
        per member."""
        self.learning.sync_worker(self.worker)
        result = self.worker.run_round(t_env=t_env, greedy=True, record=False)
        per, has_wins = self.ctx.run.test_episodes, self.ctx.info.has_wins
        records = []
        for k in range(self.ctx.n_ensemble):
            sl = slice(k * per, (k + 1) * per)
            records.append(
                EvalRecord(
                    member=k,
                    t_env=t_env,
                    episode=episodes,
                    test_return_mean=float(result.returns[sl].mean()),
                    test_won_mean=float(result.won[sl].mean()) if has_wins else None,
                    wall_s=wall_s,
                    updates=self.learning.version,
                )
            )
        return records

    def progress_text(self, records: list[EvalRecord]) -> str:
        """The greedy evaluation's figures (means over members) for a progress line."""
        text = f"test_return {np.mean([r.test_return_mean for r in records]):.2f}"
        if self.ctx.info.has_wins:
            text = f"win rate {np.mean([r.test_won_mean for r in records]):.2f} " + text
        return f"{text} updates {self.learning.version}"

    def state(self) -> dict[str, Any]:
        """The test worker's and its envs' random states, for a checkpoint."""
        return {
            "test_worker_rng": self.worker.gen.get_state(),
            "test_env_rng": rng_state(self.venv),
        }

    def load_state(self, state: dict[str, Any]) -> None:
        self.worker.gen.set_state(state["test_worker_rng"])
        if "test_env_rng" in state:  # absent from checkpoints of earlier commits
            set_rng_state(self.venv, state["test_env_rng"])
