"""Ray-side parts of the no-env transport bound of `credit bench scaling`.

Imports Ray: import this module only after `cluster.launch.ray_cluster.apply_ray_environment()`.

`SyntheticActor` is `RolloutActor.run` without the env: the same coordinator `sync` per
round, the same `BufferClient` inserting a round of `num_envs` whole episodes per request,
but the episodes are pre-built random arrays of the env's schema, so the loop measures the
transport (Ray RPC, msgpack, TCP, the service's validation, log and fsync) alone.
`Sampler` is the learner side: a thread sampling batches as fast as the service serves them.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time

import numpy as np
import ray

from actors.rollout import clock_seq
from buffer_service.client import BufferClient, RateLimitedError
from buffer_service.episode import EpisodeSchema
from cluster.bench.common import synthetic_episode
from cluster.messages import ActorCounters, ActorStats
from cluster.metrics.loop_stats import LoopStats


@ray.remote(max_restarts=0, max_concurrency=2)
class SyntheticActor:
    """Inserts pre-built rounds as fast as the service acknowledges them.

    Args:
        actor_id: the id its episodes carry.
        schema: `EpisodeSchema.to_dict()` of the env.
        length: transitions per synthetic episode (the measured mean of the real env).
        num_envs: episodes per round (one insert request), as a rollout actor's round.
        buffer: (host, port, token) of the buffer service.
        coordinator: the `Coordinator` actor counting steps and holding the stop flag.
    """

    def __init__(
        self,
        actor_id: int,
        schema: dict,
        length: int,
        num_envs: int,
        buffer: tuple[str, int, str],
        coordinator,
    ):
        self.actor_id = actor_id
        sch = EpisodeSchema.from_dict(schema)
        rng = np.random.default_rng(actor_id)
        self.round = [synthetic_episode(sch, length, actor_id, rng) for _ in range(num_envs)]
        host, port, token = buffer
        self.client = BufferClient(host, port, token=token, schema=sch, max_retries=1000)
        self.coordinator = coordinator
        self.seq = 0
        self.counters = ActorCounters()  # act_s: building the round's records (no env)

    def stats(self) -> ActorStats:
        """Loop counters in `RolloutActor.stats` form."""
        return self.counters.snapshot(os.getpid(), 0)

    def run(self) -> None:
        """Sync, insert one round, repeat until the coordinator says stop."""
        c = self.counters
        steps = episodes = 0
        while True:
            started = time.perf_counter()
            stop = ray.get(self.coordinator.sync.remote(self.actor_id, 0, steps, episodes)).stop
            if stop:
                return
            acting = time.perf_counter()
            eps = []
            for ep in self.round:
                self.seq = clock_seq(self.seq)
                eps.append(dataclasses.replace(ep, episode_seq=self.seq))
            inserting = time.perf_counter()
            try:
                self.client.insert(eps)
            except RateLimitedError:
                c.insert_refusals += 1
                steps = episodes = 0
                continue
            done = time.perf_counter()
            steps, episodes = sum(len(e.reward) for e in eps), len(eps)
            c.rounds += 1
            c.env_steps += steps
            c.sync_s += acting - started
            c.act_s += inserting - acting
            c.insert_s += done - inserting


class Sampler:
    """The learner side of the transport bound: samples `batch_size` episodes from `table`
    in a loop on its own thread and counts them in a `LoopStats` (no training, no updates).

    Args:
        client: a BufferClient of its own.
        table, batch_size: what the learner would sample.
    """

    def __init__(self, client: BufferClient, table: str, batch_size: int):
        self.client, self.table, self.batch_size = client, table, batch_size
        self.stats = LoopStats()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="sampler", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(60)
        self.client.close()

    def _loop(self) -> None:
        while not self._stop.is_set():
            started = time.perf_counter()
            self.stats.sample_requests += 1
            try:
                eps = self.client.sample_episodes(self.table, self.batch_size, timeout_s=1.0)
            except RateLimitedError:
                self.stats.sample_timeouts += 1
                continue
            finally:
                self.stats.sample_s += time.perf_counter() - started
            self.stats.consumed_env_steps += sum(int(e.filled.sum()) for e in eps)
