"""The Ray actors of `--mode cluster`: a coordinator and the rollout actors.

The coordinator holds the latest weights as one object-store reference per version (the
learner calls `ray.put` once per version; every actor reads the same object), the global
env-step count that drives ε, and the stop flag. A rollout actor wraps a plain
`RolloutWorker` and a `BufferClient`: collect a round, insert it, sync, repeat.
"""

from __future__ import annotations

import logging
import os
import time
from typing import Any

import ray

from actors.envs.registry import make_vec_env
from actors.rollout import RolloutWorker, clock_seq
from buffer_service.client import BufferClient, RateLimitedError
from cluster.messages import (
    ActorConfig,
    ActorCounters,
    ActorDescription,
    ActorStats,
    ActorWork,
    BufferAddress,
    ProgressReport,
    SyncReply,
)
from cluster.metrics.exporters import ActorMetrics
from cluster.metrics.http import serve

log = logging.getLogger(__name__)

INSERT_WAIT_S = 1.0  # one insert's wait for the rate limiter before the actor checks `stop`


@ray.remote(num_cpus=0)
class Coordinator:
    """Weights, progress and the stop flag, shared by the learner and the actors."""

    def __init__(self, t_env: int = 0, episodes: int = 0):
        self.version = -1
        self.weights: Any = None
        self.t_env, self.episodes = t_env, episodes
        self.per_actor: dict[int, ActorWork] = {}
        self.stop = False

    def publish(self, version: int, boxed_ref: list) -> None:
        """Adopt weights `version`; `boxed_ref` is [ObjectRef] (boxed so Ray passes the
        reference itself, not the weights)."""
        if version > self.version:
            self.version, self.weights = version, boxed_ref[0]

    def sync(self, actor_id: int, have_version: int, steps: int, episodes: int) -> SyncReply:
        """Count an actor's new work; return the newest weights if newer than `have_version`."""
        self.t_env += steps
        self.episodes += episodes
        self.per_actor[actor_id] = self.per_actor.get(actor_id, ActorWork()).plus(steps, episodes)
        newer = [self.weights] if self.version > have_version and self.weights is not None else None
        return SyncReply(self.version, newer, self.t_env, self.stop)

    def progress(self) -> ProgressReport:
        return ProgressReport(self.t_env, self.episodes, dict(self.per_actor))

    def request_stop(self) -> None:
        self.stop = True


# max_concurrency=2: `describe` answers while `run` is looping in the other thread.
@ray.remote(max_restarts=-1, max_task_retries=0, max_concurrency=2)
class RolloutActor:
    """Steps `num_envs` envs with the latest published policy and inserts whole episodes.

    Ray restarts the process if it dies; the launcher then calls `run` again. Episode numbers
    come from `clock_seq`, so a restarted actor never reuses one (no insert of the new life is
    mistaken for a duplicate of the old one) and an episode is inserted whole or not at all.
    The envs and the action sampling are seeded from `cfg.seed` (`messages.actor_seed`), and
    the acting network is built from the learner's `ActingSpec`.
    """

    def __init__(self, cfg: ActorConfig, buffer: BufferAddress, coordinator: str):
        self.actor_id = cfg.actor_id
        self.send_state = cfg.send_state
        venv = make_vec_env(cfg.env_id, cfg.num_envs, seed=cfg.seed, **cfg.env_args)
        self.worker = RolloutWorker.from_spec(
            venv, cfg.acting, cfg.exploration, cfg.actor_id, cfg.seed, next_seq=clock_seq
        )
        self.client = BufferClient(
            buffer.host,
            buffer.port,
            token=buffer.token,
            schema=venv.info.schema(),
            max_retries=1000,
        )
        # Looked up by name: a handle as a constructor argument would live in the object
        # store, which Ray cannot guarantee to a restarted actor (ray-project/ray#53727).
        self.coordinator = ray.get_actor(coordinator)
        self.metrics = ActorMetrics(cfg.actor_id) if cfg.metrics else None
        host = "127.0.0.1"
        if cfg.bind_host not in ("127.0.0.1", "localhost"):
            host = ray.util.get_node_ip_address()  # this actor's node, reachable from the head
        self.endpoint = serve(self.metrics.registry, host=host) if self.metrics else None
        self.counters = ActorCounters()  # cumulative over this process's life (`stats`)

    def describe(self) -> ActorDescription:
        """pid and metrics endpoint of this actor process."""
        endpoint = tuple(self.endpoint) if self.endpoint else None
        return ActorDescription(self.actor_id, os.getpid(), endpoint)

    def stats(self) -> ActorStats:
        """This process's loop counters with its pid and weights version."""
        return self.counters.snapshot(os.getpid(), self.worker.version)

    def run(self) -> ActorWork:
        """Collect and insert until the coordinator says stop; returns this life's totals."""
        steps = episodes = 0
        total = ActorWork()
        c = self.counters
        while True:
            started = time.perf_counter()
            reply: SyncReply = ray.get(
                self.coordinator.sync.remote(self.actor_id, self.worker.version, steps, episodes)
            )
            if reply.stop:
                return total
            if reply.weights is not None:
                weights = ray.get(reply.weights[0])
                self.worker.set_weights(weights)
                if self.metrics:
                    self.metrics.set_weights_version(weights.version)
            acting = time.perf_counter()
            result = self.worker.run_round(t_env=reply.t_env)
            inserting = time.perf_counter()
            self._insert(result.episodes)
            done = time.perf_counter()
            steps, episodes = result.env_steps, len(result.episodes)
            total = total.plus(steps, episodes)
            c.rounds += 1
            c.env_steps += steps
            c.sync_s += acting - started
            c.act_s += inserting - acting
            c.insert_s += done - inserting
            if self.metrics:
                self.metrics.record(episodes, steps)

    def _insert(self, episodes: list) -> None:
        """Insert, waiting out back-pressure (the learner is behind) for as long as it takes,
        and asking the coordinator between waits whether to stop: at the end of a run the
        loop returns within INSERT_WAIT_S instead of sitting in an insert that the service's
        shutdown would cut."""
        while True:
            try:
                self.client.insert(episodes, timeout_s=INSERT_WAIT_S, state=self.send_state)
                return
            except RateLimitedError:
                self.counters.insert_refusals += 1
                reply: SyncReply = ray.get(
                    self.coordinator.sync.remote(self.actor_id, self.worker.version, 0, 0)
                )
                if reply.stop:
                    return
