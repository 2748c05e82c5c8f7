"""RolloutWorker: steps a batch of envs with the current policy and records whole episodes.

Actors only act and record; returns, targets and advantages are the learner's business.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch.nn import functional as F

from actors.envs.base import VecEnv
from actors.policy import ExplorationConfig, select_actions
from buffer_service.episode import Episode
from learner.batch import AgentInputLayout
from learner.networks import ActingSpec, AgentNet, VersionedWeights
from learner.timers import timed


def clock_seq(last: int) -> int:
    """Episode numbers from the wall clock in microseconds, strictly increasing: a restarted
    actor never reuses a number its previous life inserted (inserts are idempotent on
    (actor_id, episode_seq), so a reused number would be dropped as a duplicate)."""
    return max(last + 1, time.time_ns() // 1000)


@dataclass(frozen=True)
class RoundResult:
    """One episode from every env of the worker.

    Attributes:
        episodes: in env order; env k belongs to ensemble member k // envs_per_member.
        returns: [num_envs] undiscounted episode returns.
        won: [num_envs] battle won (False where the env has no wins).
        env_steps: transitions recorded in this round.
    """

    episodes: list[Episode]
    returns: np.ndarray
    won: np.ndarray
    env_steps: int


class RolloutWorker:
    """Acts in `venv` with an AgentNet of `n_ensemble` members (E = 1 for a normal run).

    Calling loop::

        worker = RolloutWorker(venv, agent_net, "q", ExplorationConfig(), actor_id=3)
        # episode_seq: next_seq(last) numbers the episodes (default last + 1); a worker that
        # may restart uses a source that never repeats, e.g. `clock_seq`.
        worker.set_weights(learner.get_weights())      # adopted only if newer
        episodes = worker.collect(8, t_env=t)          # list[Episode]
    """

    def __init__(
        self,
        venv: VecEnv,
        agent: AgentNet,
        policy_kind: str,
        exploration: ExplorationConfig,
        n_ensemble: int = 1,
        actor_id: int = 0,
        seed: int = 0,
        next_seq: Callable[[int], int] | None = None,
    ):
        if venv.num_envs % n_ensemble:
            raise ValueError(
                f"num_envs={venv.num_envs} is not a multiple of n_ensemble={n_ensemble}"
            )
        self.layout = AgentInputLayout(venv.info.obs_shape, venv.info.n_actions, venv.info.n_agents)
        if agent.input_dim != self.layout.width:
            raise ValueError(
                f"the acting network takes {agent.input_dim} inputs per agent, but this env's "
                f"agent input (obs + last action + id, {self.layout.parts}) is "
                f"{self.layout.width} wide"
            )
        self.venv, self.agent, self.kind = venv, agent, policy_kind
        self.exploration, self.n_ensemble, self.actor_id = exploration, n_ensemble, actor_id
        self.info = venv.info
        self.gen = torch.Generator().manual_seed(seed)
        self.version = -1
        self.episode_seq = 0
        self.next_seq = next_seq or (lambda last: last + 1)
        self.t_env = 0

    @classmethod
    def from_spec(
        cls,
        venv: VecEnv,
        spec: ActingSpec,
        exploration: ExplorationConfig,
        actor_id: int = 0,
        seed: int = 0,
        next_seq: Callable[[int], int] | None = None,
    ) -> RolloutWorker:
        """A worker acting with its own network, built from the learner's description
        (`Learner.acting`); its weights arrive through `set_weights`.

        Args:
            venv: the envs to step.
            spec: the acting network's description.
            exploration: epsilon schedule (value family).
            actor_id, seed, next_seq: as for the constructor.
        Returns:
            A worker of one ensemble member.
        """
        agent = spec.build(1).requires_grad_(False)
        return cls(venv, agent, spec.policy_kind, exploration, 1, actor_id, seed, next_seq)

    def follow(self, version: int) -> None:
        """Record that the (shared, in-process) agent network now holds `version`; used when
        the worker acts with the learner's own module instead of a copy."""
        self.version = version

    def set_weights(self, weights: VersionedWeights) -> bool:
        """Adopt `weights` if newer than the current ones; returns whether it did."""
        if weights.version <= self.version:
            return False
        weights.load_into(self.agent)
        self.version = weights.version
        return True

    def collect(
        self, num_episodes: int, t_env: int | None = None, greedy: bool = False
    ) -> list[Episode]:
        """At least `num_episodes` episodes (whole rounds of `num_envs`)."""
        episodes: list[Episode] = []
        while len(episodes) < num_episodes:
            episodes.extend(self.run_round(t_env, greedy).episodes)
        return episodes

    def run_round(
        self,
        t_env: int | None = None,
        greedy: bool = False,
        on_step: Callable[[], None] | None = None,
        record: bool = True,
    ) -> RoundResult:
        """Reset every env and play one episode in each until all have ended.

        Args:
            t_env: the env-step count that sets epsilon (default: this worker's own count).
            greedy: act greedily (evaluation) instead of exploring.
            on_step: called after the reset and after every step of the envs, e.g. to take
                a snapshot of a battle for a replay.
            record: keep the episodes (False: only the returns, wins and step count, with
                one step of observations held at a time; what an evaluation needs: on
                bane_vs_bane 60 test envs would otherwise hold 0.4 GB of observations,
                and their copies as much again). The play is the same either way.
        """
        info, venv = self.info, self.venv
        k, n, a = venv.num_envs, info.n_agents, info.n_actions
        e, m = self.n_ensemble, venv.num_envs // self.n_ensemble
        limit = info.episode_limit
        eps = self.exploration.epsilon(self.t_env if t_env is None else t_env)
        rows = limit + 1 if record else 1  # time rows of obs, state and avail
        obs = np.zeros((k, rows, n, info.obs_shape), np.float32)
        state = np.zeros((k, rows, info.state_shape), np.float32) if record else None
        avail = np.zeros((k, rows, n, a), np.uint8)
        actions = np.zeros((k, limit, n), np.int64)
        reward = np.zeros((k, limit), np.float32)
        terminated = np.zeros((k, limit), bool)
        length = np.zeros(k, np.int64)
        won = np.zeros(k, bool)
        venv.reset()
        if on_step:
            on_step()
        active = np.ones(k, bool)
        h = self.agent.init_hidden(e, m * n)
        last = torch.zeros(e, m * n, a)
        ids = torch.eye(n).repeat(m, 1).expand(e, m * n, n)
        t = 0
        with torch.no_grad():
            while active.any() and t < limit:
                row = t if record else 0
                with timed("env"):
                    obs[:, row], avail[:, row] = venv.get_obs(), venv.get_avail_actions()
                    if record:
                        state[:, row] = venv.get_state()
                # the order of AgentInputLayout: own obs, last action, agent id
                with timed("policy"):
                    x = torch.cat(
                        [torch.from_numpy(obs[:, row]).reshape(e, m * n, -1), last, ids], -1
                    )
                    out, h = self.agent(x, h)
                    av = torch.from_numpy(avail[:, row]).reshape(e, m * n, a).bool()
                    act = select_actions(out, av, self.kind, eps, greedy, self.gen)
                    last = F.one_hot(act, a).float()
                    acts = act.view(k, n).numpy()
                with timed("env"):
                    r, done, infos = venv.step(acts, active)
                if on_step:
                    on_step()
                actions[:, t], reward[:, t] = acts, np.where(active, r, 0.0)
                for j in np.flatnonzero(active & done):
                    terminated[j, t] = not infos[j].get("episode_limit", False)
                    won[j] = bool(infos[j].get("battle_won", False))
                    length[j] = t + 1
                active &= ~done
                t += 1
            length[active] = t  # cut by our own loop bound: a time-limit cut, not terminal
            if record:
                obs[:, t], state[:, t], avail[:, t] = (
                    venv.get_obs(),
                    venv.get_state(),
                    venv.get_avail_actions(),
                )
        episodes = []
        if record:
            episodes = [
                self._episode(j, length[j], obs, state, avail, actions, reward, terminated)
                for j in range(k)
            ]
        steps = int(length.sum())
        if t_env is None:
            self.t_env += steps
        return RoundResult(episodes, reward.sum(1), won, steps)

    def _episode(self, j, t, obs, state, avail, actions, reward, terminated) -> Episode:
        # Row t (the observation after an env's last step) was written at the start of the
        # next loop iteration or after the loop; rows past it are never read.
        self.episode_seq = self.next_seq(self.episode_seq)
        return Episode(
            obs=obs[j, : t + 1].copy(),
            state=state[j, : t + 1].copy(),
            avail_actions=avail[j, : t + 1].copy(),
            actions=actions[j, :t].copy(),
            reward=reward[j, :t].copy(),
            terminated=terminated[j, :t].copy(),
            filled=np.ones(t, bool),
            actor_id=self.actor_id,
            episode_seq=self.episode_seq,
            policy_version=max(self.version, 0),
        )
