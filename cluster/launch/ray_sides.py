"""The distributed sides of `cluster.loop.TrainLoop` (`--mode cluster`): Ray rollout actors
with their coordinator (`RayActing`), and the buffer service over TCP (`ServiceData`)."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import ray

from buffer_service.client import BufferClient, RateLimitedError
from buffer_service.episode import EpisodeBatch
from cluster.batches import BatchPairer
from cluster.context import RunContext
from cluster.core import write_json
from cluster.evaluation import EvalRecord
from cluster.launch.buffer_proc import BufferProcess
from cluster.launch.ray_actors import Coordinator, RolloutActor
from cluster.learning import Learning
from cluster.loop import Pair, drop_stale
from cluster.messages import ActorConfig, ActorDescription, BufferAddress, actor_seed
from cluster.metrics.discovery import register_run_sd, unregister_run_sd
from cluster.metrics.discovery import write_file_sd as write_sd
from cluster.metrics.exporters import LearnerMetrics
from cluster.metrics.http import serve
from cluster.metrics.loop_stats import LoopStats

log = logging.getLogger(__name__)


class ServiceData:
    """Batches from the buffer service, whose limiter paces the learner against the actors.

    Args:
        ctx: the run (data plan, schema, run.max_policy_lag).
        learning: the learner (its version).
        stats: the loop's counters.
        buffer: the service's child process (address, token).
        metrics: the learner's exporter, or None.
    """

    def __init__(
        self,
        ctx: RunContext,
        learning: Learning,
        stats: LoopStats,
        buffer: BufferProcess,
        metrics: LearnerMetrics | None,
    ) -> None:
        self.ctx, self.learning, self.stats = ctx, learning, stats
        self.buffer, self.metrics = buffer, metrics
        self.timeout_s = ctx.cfg.cluster.sample_timeout_s
        self.pairer = BatchPairer(ctx.plan, self._sample)
        self.client: BufferClient | None = None

    def connect(self) -> None:
        self.client = BufferClient(
            self.buffer.host,
            self.buffer.port,
            token=self.buffer.token,
            schema=self.ctx.info.schema(),
            # Few retries (about 3 s of backoff): the loop is what restarts a dead service
            # (`RayActing.act`), so it must not sit in a request retrying against it.
            max_retries=6,
        )

    def close(self) -> None:
        if self.client:
            self.client.close()

    def catch_up(self) -> Iterator[Pair]:
        """Nothing: actors wait in their inserts while the learner samples in `batches`."""
        return iter(())

    def batches(self, new_episodes: int) -> Iterator[Pair]:
        """At most one batch (pair) per iteration: as soon as the limiter allows it."""
        pair = self.pairer.next()
        if pair is not None:
            yield pair

    def _sample(self, table: str, n: int) -> EpisodeBatch | None:
        """A batch from `table`, or None if the limiter kept it back or every episode was
        staler than run.max_policy_lag."""
        started = time.perf_counter()
        self.stats.sample_requests += 1
        try:
            episodes = self.client.sample_episodes(table, n, timeout_s=self.timeout_s)
        except RateLimitedError:
            self.stats.sample_timeouts += 1
            return None
        except ConnectionError as e:  # the service is down: RayActing.act restarts it
            log.warning("sample from %s failed (%s); checking the buffer service", table, e)
            return None
        finally:
            self.stats.sample_s += time.perf_counter() - started
        limit, version = self.ctx.run.max_policy_lag, self.learning.version
        episodes, lags = drop_stale(episodes, version, limit, self.stats)
        if self.metrics:
            self.metrics.record_policy_lag(lags)
        return EpisodeBatch.from_episodes(episodes) if episodes else None

    def write(self, folder: Path) -> None:
        """Nothing: the service keeps its own durable log and snapshots (OUT/buffer/data)."""

    def read(self, folder: Path) -> None:
        """Nothing: the service restores its folder when it starts."""

    def state(self) -> dict[str, Any]:
        return {"dropped_stale": self.stats.dropped_stale}

    def load_state(self, state: dict[str, Any]) -> None:
        self.stats.dropped_stale = state.get("dropped_stale", 0)


class RayActing:
    """`cluster.actors` Ray rollout actors, their coordinator, and their supervision.

    Args:
        ctx: the run.
        learning: the learner (its acting network, weights and version).
        out: the run's folder (cluster.json, targets.json).
        buffer: the buffer service's child process (restarted here if it dies).
        stats: the loop's counters (publish time).
        metrics: the learner's exporter, or None.
    """

    def __init__(
        self,
        ctx: RunContext,
        learning: Learning,
        out: Path,
        buffer: BufferProcess,
        stats: LoopStats,
        metrics: LearnerMetrics | None,
    ) -> None:
        self.ctx, self.learning, self.out = ctx, learning, out
        self.buffer, self.stats, self.metrics = buffer, stats, metrics
        self.ccfg = ctx.cfg.cluster
        self.coordinator = None
        self.actors: list = []
        self.loops: dict = {}  # ObjectRef of a running `run` -> actor index
        self.restarts = 0
        self.endpoints: list[tuple[str, int]] = []
        # this run's entry in cluster.metrics.discovery.runs_sd_dir()
        self.sd_link: Path | None = None
        self.learner_endpoint: tuple[str, int] | None = None
        self.described_buffer_restarts = 0

    def actor_config(self, actor_id: int) -> ActorConfig:
        """What actor `actor_id` is configured with: its own section of the run, no more."""
        cfg = self.ctx.cfg
        return ActorConfig(
            actor_id=actor_id,
            env_id=cfg.env.id,
            env_args=dict(cfg.env.args),
            num_envs=cfg.run.num_envs,
            seed=actor_seed(cfg.run.seed, actor_id),
            exploration=cfg.exploration,
            acting=self.learning.learner.acting,
            metrics=self.ccfg.metrics,
            bind_host=self.ccfg.bind_host,
            send_state=self.ctx.plan.store_state,
        )

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self, t_env: int, episodes: int) -> None:
        """Start the coordinator, counting from the loop's totals, and the rollout actors (the
        buffer service is running)."""
        name = f"credit-coordinator-{os.getpid()}-{time.time_ns()}"  # one per run and Ray job
        self.coordinator = Coordinator.options(name=name).remote(t_env, episodes)
        self.publish()
        address = BufferAddress(self.buffer.host, self.buffer.port, self.buffer.token)
        for i in range(self.ccfg.actors):
            actor = RolloutActor.options(num_cpus=self.ccfg.actor_cpus).remote(
                self.actor_config(i), address, name
            )
            self.actors.append(actor)
        for i in range(len(self.actors)):
            self._start_loop(i)
        if self.metrics:
            self.learner_endpoint = serve(self.metrics.registry, host=self.ccfg.bind_host)
        self._describe()

    def shutdown(self) -> None:
        """Stop the actors' loops, then the actors; take the run out of the live runs."""
        if self.sd_link is not None:
            unregister_run_sd(self.sd_link)
            self.sd_link = None
        if self.coordinator is not None:
            ray.get(self.coordinator.request_stop.remote())
            # Loops blocked on back-pressure may not notice for a while; their unacknowledged
            # rounds are simply not inserted, so a short wait then a kill loses nothing.
            ray.wait(list(self.loops), num_returns=len(self.loops), timeout=5)
        for a in self.actors:
            ray.kill(a, no_restart=True)

    @staticmethod
    def _ask(method, timeout_s: float = 120.0):
        """Call an actor method, waiting out a restart of its process (Ray queues nothing for
        a restarting actor: the call fails with ActorUnavailableError and is tried again)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return ray.get(method.remote(), timeout=timeout_s)
            except ray.exceptions.ActorUnavailableError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)

    def _describe(self) -> None:
        """Write OUT/cluster.json (pids and endpoints of the learner, buffer service and actors)
        and, with metrics on, OUT/targets.json: the run's own Prometheus file-SD file listing
        every exporter, labelled with the run's folder, linked into the machine's folder of
        live runs (`cluster.metrics.discovery.runs_sd_dir`) so one `credit metrics up` scrapes
        every run.
        A restarted actor process has a new pid and port, so this runs again after restarts."""
        described: list[ActorDescription] = [self._ask(a.describe) for a in self.actors]
        topology = {
            "learner": {
                "pid": os.getpid(),
                "metrics": list(self.learner_endpoint) if self.metrics else None,
            },
            "buffer": {
                "pid": self.buffer.pid,
                "port": self.buffer.port,
                "metrics_port": self.buffer.metrics_port,
            },
            "actors": [d.as_json() for d in described],
        }
        write_json(self.out / "cluster.json", topology)
        if not self.metrics:
            return
        self.endpoints = [self.learner_endpoint, *(d.metrics for d in described)]
        if self.buffer.metrics_port:
            self.endpoints.append((self.buffer.host, int(self.buffer.metrics_port)))
        labels = {"job": "credit", "run": str(self.out.resolve())}
        write_sd(self.out / "targets.json", self.endpoints, labels)
        if self.sd_link is None:
            self.sd_link = register_run_sd(self.out / "targets.json")

    def _start_loop(self, i: int) -> None:
        self.loops[self.actors[i].run.remote()] = i

    # -- the acting side of the loop ---------------------------------------------------------
    def act(self, t_env: int, episodes: int) -> tuple[int, int]:
        """Restart what died; return the env steps and episodes the actors reported beyond
        the loop's totals `t_env` and `episodes` (the coordinator's totals less the loop's)."""
        self._supervise()
        report = ray.get(self.coordinator.progress.remote())
        return report.t_env - t_env, report.episodes - episodes

    def updated(self, seconds: float, metrics: dict[str, float]) -> None:
        """Record the update and its metrics; publish the weights every
        cluster.publish_interval updates."""
        learner = self.learning.learner
        if self.metrics:
            self.metrics.record_update(seconds, metrics, learner.updates)
            if "kl_masked_fraction" in metrics:
                self.metrics.set_kl_masked_fraction(metrics["kl_masked_fraction"])
        if learner.updates % self.ccfg.publish_interval == 0:
            started = time.perf_counter()
            self.publish()
            self.stats.publish_s += time.perf_counter() - started

    def evaluated(self, records: list[EvalRecord]) -> None:
        if self.metrics:
            self.metrics.record_test(records[0].test_return_mean, records[0].test_won_mean)

    def publish(self) -> None:
        weights = self.learning.learner.get_weights()
        ref = ray.put(weights)  # once per version; every actor reads this one object
        ray.get(self.coordinator.publish.remote(weights.version, [ref]))

    def _supervise(self) -> None:
        """Restart the buffer service and actor loops that died (Ray restarts the processes)."""
        if self.buffer.ensure_running():
            log.warning("buffer service restarted (%d so far)", self.buffer.restarts)
        done, _ = ray.wait(list(self.loops), num_returns=len(self.loops), timeout=0)
        for ref in done:
            i = self.loops.pop(ref)
            try:
                ray.get(ref)
                log.warning("actor %d's loop returned early; starting it again", i)
            except (ray.exceptions.RayActorError, ray.exceptions.ActorUnavailableError) as e:
                self.restarts += 1
                if self.metrics:
                    self.metrics.actor_restarted()
                log.warning(
                    "actor %d died (%s); Ray restarts it, loop %d",
                    i,
                    type(e).__name__,
                    self.restarts,
                )
            self._start_loop(i)
        if done or self.buffer.restarts != self.described_buffer_restarts:
            self.described_buffer_restarts = self.buffer.restarts
            self._describe()

    def state(self) -> dict[str, Any]:
        return {"actor_restarts": self.restarts}

    def load_state(self, state: dict[str, Any]) -> None:
        self.restarts = state.get("actor_restarts", 0)
