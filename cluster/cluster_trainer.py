"""`credit train --mode cluster`: Ray rollout actors, the buffer service, and this process as
the learner. Same config, outputs and checkpoints as `--mode local`.

The learner loop: sample a batch from the service (the sample-to-insert limiter paces it
against the actors), measure policy lag and drop episodes older than max_policy_lag, update,
publish the weights (one `ray.put` per version), evaluate and checkpoint on schedule, and
restart any rollout actor loop whose process died.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

import ray
import yaml

from buffer_service.client import BufferClient, RateLimitedError
from buffer_service.episode import Episode, EpisodeBatch
from cluster.batches import BatchPairer
from cluster.buffer_proc import BufferProcess
from cluster.loop_stats import LoopStats
from cluster.metrics import (
    LearnerMetrics,
    register_run_sd,
    serve,
    unregister_run_sd,
    write_file_sd,
)
from cluster.ray_actors import Coordinator, RolloutActor
from cluster.trainer import EvalRecord, Progress, TrainerCore, write_json

log = logging.getLogger(__name__)


class ClusterTrainer:
    """Rollout actors on Ray, the buffer service as a child process, the learner here.

    Calling loop::

        cluster_ray.connect(address, num_cpus)      # ray.init on loopback
        trainer = ClusterTrainer(cfg, out_dir)
        trainer.restore(out_dir / "checkpoint")     # optional (--resume)
        trainer.start()
        try:
            trainer.train(on_eval=...)
        finally:
            trainer.shutdown()
    """

    def __init__(self, cfg, out: Path):
        self.core = core = TrainerCore(cfg, 1, Path(out) / "checkpoint", actors=cfg.cluster.actors)
        self.cfg, self.out = cfg, Path(out)
        self.ccfg = cfg.cluster
        self.plan = core.plan
        self.batches = BatchPairer(self.plan, self._sample)
        self.buffer = BufferProcess(
            self.plan.tables,
            core.info.schema(),
            self.out / "buffer",
            fsync=self.ccfg.fsync,
            metrics=self.ccfg.metrics,
            host=self.ccfg.bind_host,
        )
        self.client: BufferClient | None = None
        self.coordinator = None
        self.actors: list = []
        self.loops: dict = {}  # ObjectRef of a running `run` -> actor index
        self.restarts = 0
        self.dropped_stale = 0
        self.metrics = LearnerMetrics() if self.ccfg.metrics else None
        self.endpoints: list[tuple[str, int]] = []
        self.sd_link: Path | None = None  # this run's entry in cluster.metrics.runs_sd_dir()
        self.learner_endpoint: tuple[str, int] | None = None
        self.described_buffer_restarts = 0
        self.stats = LoopStats()
        self.stop_requested = False  # set from another thread to end `train` early

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        """Start the buffer service, the coordinator and the rollout actors."""
        self.buffer.start()
        schema = self.core.info.schema()
        self.client = BufferClient(
            self.buffer.host,
            self.buffer.port,
            token=self.buffer.token,
            schema=schema,
            # Few retries (about 3 s of backoff): this loop is what restarts a dead service
            # (`_supervise`), so it must not sit in a request retrying against it.
            max_retries=6,
        )
        name = f"credit-coordinator-{os.getpid()}-{time.time_ns()}"  # one per run and Ray job
        self.coordinator = Coordinator.options(name=name).remote(
            self.core.t_env, self.core.episodes
        )
        self.publish()
        data = yaml.safe_dump(self.cfg.to_yaml_dict())  # small: inlined in the creation task
        address = (self.buffer.host, self.buffer.port, self.buffer.token)
        for i in range(self.ccfg.actors):
            actor = RolloutActor.options(num_cpus=self.ccfg.actor_cpus).remote(
                i, data, address, name, self.ccfg.metrics
            )
            self.actors.append(actor)
        for i in range(len(self.actors)):
            self._start_loop(i)
        if self.metrics:
            self.learner_endpoint = serve(self.metrics.registry, host=self.ccfg.bind_host)
        self._describe()
        log.info(
            "%d rollout actors, buffer service on %s:%d",
            len(self.actors),
            self.buffer.host,
            self.buffer.port,
        )

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
        live runs (`cluster.metrics.runs_sd_dir`) so one `credit metrics up` scrapes every run.
        A restarted actor process has a new pid and port, so this runs again after restarts."""
        described = [self._ask(a.describe) for a in self.actors]
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
            "actors": described,
        }
        write_json(self.out / "cluster.json", topology)
        if not self.metrics:
            return
        self.endpoints = [self.learner_endpoint, *(tuple(d["metrics"]) for d in described)]
        if self.buffer.metrics_port:
            self.endpoints.append((self.buffer.host, int(self.buffer.metrics_port)))
        labels = {"job": "credit", "run": str(self.out.resolve())}
        write_file_sd(self.out / "targets.json", self.endpoints, labels)
        if self.sd_link is None:
            self.sd_link = register_run_sd(self.out / "targets.json")

    def _start_loop(self, i: int) -> None:
        self.loops[self.actors[i].run.remote()] = i

    def shutdown(self) -> None:
        """Stop the actors' loops, then the actors and the buffer service; take the run out
        of the machine's live runs."""
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
        if self.client:
            self.client.close()
        self.buffer.stop()

    # -- the learner loop --------------------------------------------------------------------
    def publish(self) -> None:
        weights = self.core.learner.get_weights()
        ref = ray.put(weights)  # once per version; every actor reads this one object
        ray.get(self.coordinator.publish.remote(weights.version, [ref]))

    def train(
        self, on_eval: Callable[[list[EvalRecord]], None] | None = None, progress: bool = False
    ) -> None:
        core, run = self.core, self.cfg.run
        bar = Progress(run.t_max) if progress else None
        while core.t_env < run.t_max and not self.stop_requested:
            self._supervise()
            pair = self.batches.next()
            if pair is not None:
                batch, extra = pair
                started = time.perf_counter()
                core.update(batch, extra)
                seconds = time.perf_counter() - started
                self.stats.updates += 1
                self.stats.update_s += seconds
                self.stats.consumed_env_steps += int(batch.filled.sum())
                if self.metrics:
                    self.metrics.record_update(seconds, core.last_metrics, core.learner.updates)
                    if "kl_masked_fraction" in core.last_metrics:
                        self.metrics.set_kl_masked_fraction(core.last_metrics["kl_masked_fraction"])
                if core.learner.updates % self.ccfg.publish_interval == 0:
                    started = time.perf_counter()
                    self.publish()
                    self.stats.publish_s += time.perf_counter() - started
            core.t_env, core.episodes, _ = ray.get(self.coordinator.progress.remote())
            core.periodic(self._on_eval(on_eval), bar, self.loop_state)
        if bar:
            bar.close()

    def _on_eval(self, on_eval):
        def handler(records: list[EvalRecord]) -> None:
            if self.metrics:
                self.metrics.record_test(records[0].test_return_mean, records[0].test_won_mean)
            if on_eval:
                on_eval(records)

        return handler

    def _sample(self, table: str, n: int) -> EpisodeBatch | None:
        """A batch from `table`, or None if the limiter kept it back or every episode was
        staler than max_policy_lag."""
        started = time.perf_counter()
        self.stats.sample_requests += 1
        try:
            episodes: list[Episode] = self.client.sample_episodes(
                table, n, timeout_s=self.ccfg.sample_timeout_s
            )
        except RateLimitedError:
            self.stats.sample_timeouts += 1
            return None
        except ConnectionError as e:  # the service is down: `_supervise` restarts it
            log.warning("sample from %s failed (%s); checking the buffer service", table, e)
            return None
        finally:
            self.stats.sample_s += time.perf_counter() - started
        lags = [self.core.learner.updates - ep.policy_version for ep in episodes]
        self.stats.lag_counts.update(max(0, lag) for lag in lags)
        if self.metrics:
            self.metrics.record_policy_lag(max(0, lag) for lag in lags)
        limit = self.ccfg.max_policy_lag
        if limit:
            fresh = [ep for ep, lag in zip(episodes, lags, strict=True) if lag <= limit]
            self.dropped_stale += len(episodes) - len(fresh)
            episodes = fresh
        return EpisodeBatch.from_episodes(episodes) if episodes else None

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

    def loop_state(self) -> dict:
        return {"actor_restarts": self.restarts, "dropped_stale": self.dropped_stale}

    def restore(self, path: Path) -> None:
        state = self.core.restore(path)
        self.restarts = state.get("actor_restarts", 0)
        self.dropped_stale = state.get("dropped_stale", 0)

    def save(self, path: Path) -> None:
        self.core.save(path, self.loop_state())
