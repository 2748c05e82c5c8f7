"""What crosses process boundaries in `--mode cluster`, as frozen dataclasses.

Between the learner process, the coordinator and the rollout actors (Ray calls) travel only
these types: an actor's own configuration (`ActorConfig`, not the whole run's), the buffer
service's address, the coordinator's sync reply and progress report, and each actor's
description and loop counters. The episodes themselves go to the buffer service as msgpack
(`buffer_service.codec`), never through Ray.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from actors.policy import ExplorationConfig
from learner.networks import ActingSpec


def actor_seed(run_seed: int, actor_id: int) -> int:
    """The seed of actor `actor_id`'s envs and action sampling, from the run's seed alone
    (no wall clock), so a cluster run can be repeated. Actor 0 gets `run_seed` itself: the
    one worker of `--mode local` is actor 0 too, so one cluster actor acts as local mode does.
    Other actors get decorrelated seeds (numpy's SeedSequence of (run_seed, actor_id)).

    Args:
        run_seed: run.seed.
        actor_id: 0, 1, ...
    Returns:
        A seed below 2**31.
    """
    if actor_id == 0:
        return run_seed
    return int(np.random.SeedSequence([run_seed, actor_id]).generate_state(1)[0] >> 1)


@dataclass(frozen=True)
class BufferAddress:
    """Where the buffer service listens, and its token."""

    host: str
    port: int
    token: str | None


@dataclass(frozen=True)
class ActorConfig:
    """Everything one rollout actor is configured with (and nothing else of the run).

    Attributes:
        actor_id: this actor's number (episode keys, metrics labels, its seed).
        env_id, env_args: the env to make (`actors.envs.registry.make_vec_env`).
        num_envs: envs stepped together per round (run.num_envs).
        seed: seed of the envs and of the action sampling (`actor_seed`).
        exploration: the epsilon schedule.
        acting: the acting network, as the learner describes it (`Learner.acting`).
        metrics: serve a Prometheus exporter.
        bind_host: cluster.bind_host (the exporter binds loopback unless this is not).
        send_state: send the episodes' global state (False when the learner never reads it:
            `cluster.config.plan.DataPlan.store_state`).
    """

    actor_id: int
    env_id: str
    env_args: dict[str, Any]
    num_envs: int
    seed: int
    exploration: ExplorationConfig
    acting: ActingSpec
    metrics: bool = False
    bind_host: str = "127.0.0.1"
    send_state: bool = True


@dataclass(frozen=True)
class SyncReply:
    """The coordinator's answer to an actor's `sync`.

    Attributes:
        version: the newest published weights version (-1: none yet).
        weights: [ObjectRef] of those weights when newer than the actor's, else None (boxed
            so that Ray hands over the reference, not the weights).
        t_env: the run's env steps so far (sets epsilon).
        stop: the run is over; the actor's loop returns.
    """

    version: int
    weights: list | None
    t_env: int
    stop: bool


@dataclass(frozen=True)
class ActorWork:
    """Env steps and episodes an actor contributed."""

    steps: int = 0
    episodes: int = 0

    def plus(self, steps: int, episodes: int) -> ActorWork:
        return ActorWork(self.steps + steps, self.episodes + episodes)


@dataclass(frozen=True)
class ProgressReport:
    """The coordinator's counters: the run's totals and each actor's share."""

    t_env: int
    episodes: int
    per_actor: dict[int, ActorWork] = field(default_factory=dict)


@dataclass(frozen=True)
class ActorDescription:
    """Where a rollout actor process lives (written to OUT/cluster.json)."""

    actor_id: int
    pid: int
    metrics: tuple[str, int] | None

    def as_json(self) -> dict[str, Any]:
        return {
            "actor_id": self.actor_id,
            "pid": self.pid,
            "metrics": list(self.metrics) if self.metrics else None,
        }


@dataclass
class ActorCounters:
    """An actor loop's cumulative counters over its process's life (mutable, in-process;
    `snapshot` is what leaves the process).

    Attributes:
        rounds, env_steps: rounds collected and their transitions.
        act_s: seconds in run_round (env steps and policy forward passes).
        insert_s: seconds in client.insert, incl. rate-limiter waits and the fsync.
        sync_s: seconds in coordinator.sync round trips and fetching new weights.
        insert_refusals: inserts the rate limiter refused within one wait.
    """

    rounds: int = 0
    env_steps: int = 0
    act_s: float = 0.0
    insert_s: float = 0.0
    sync_s: float = 0.0
    insert_refusals: int = 0

    def snapshot(self, pid: int, version: int) -> ActorStats:
        return ActorStats(**asdict(self), pid=pid, version=version)


@dataclass(frozen=True)
class ActorStats:
    """`ActorCounters` at one moment, with the process's pid and weights version."""

    rounds: int
    env_steps: int
    act_s: float
    insert_s: float
    sync_s: float
    insert_refusals: int
    pid: int
    version: int

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)
