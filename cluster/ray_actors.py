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
import yaml

from actors.envs.registry import make_vec_env
from actors.rollout import RolloutWorker, clock_seq
from buffer_service.client import BufferClient, RateLimitedError
from cluster.metrics import ActorMetrics, serve
from cluster.run_config import build_train_config

log = logging.getLogger(__name__)

INSERT_WAIT_S = 1.0  # one insert's wait for the rate limiter before the actor checks `stop`


@ray.remote(num_cpus=0)
class Coordinator:
    """Weights, progress and the stop flag, shared by the learner and the actors."""

    def __init__(self, t_env: int = 0, episodes: int = 0):
        self.version = -1
        self.weights: Any = None
        self.t_env, self.episodes = t_env, episodes
        self.per_actor: dict[int, dict[str, int]] = {}
        self.stop = False

    def publish(self, version: int, boxed_ref: list) -> None:
        """Adopt weights `version`; `boxed_ref` is [ObjectRef] (boxed so Ray passes the
        reference itself, not the weights)."""
        if version > self.version:
            self.version, self.weights = version, boxed_ref[0]

    def sync(self, actor_id: int, have_version: int, steps: int, episodes: int) -> tuple:
        """Count an actor's new work; return (version, [ref] or None, t_env, stop)."""
        self.t_env += steps
        self.episodes += episodes
        mine = self.per_actor.setdefault(actor_id, {"steps": 0, "episodes": 0})
        mine["steps"] += steps
        mine["episodes"] += episodes
        newer = [self.weights] if self.version > have_version and self.weights is not None else None
        return self.version, newer, self.t_env, self.stop

    def progress(self) -> tuple[int, int, dict]:
        return self.t_env, self.episodes, self.per_actor

    def request_stop(self) -> None:
        self.stop = True


# max_concurrency=2: `describe` answers while `run` is looping in the other thread.
@ray.remote(max_restarts=-1, max_task_retries=0, max_concurrency=2)
class RolloutActor:
    """Steps `run.num_envs` envs with the latest published policy and inserts whole episodes.

    Ray restarts the process if it dies; the launcher then calls `run` again. Episode numbers
    come from `clock_seq`, so a restarted actor never reuses one (no insert of the new life is
    mistaken for a duplicate of the old one) and an episode is inserted whole or not at all.
    """

    def __init__(
        self,
        actor_id: int,
        cfg_yaml: str,
        buffer: tuple[str, int, str],
        coordinator: str,
        metrics: bool,
    ):
        self.actor_id = actor_id
        self.cfg = cfg = build_train_config(yaml.safe_load(cfg_yaml))
        run = cfg.run
        seed = run.seed + 1000 * (actor_id + 1) + int(time.time()) % 1000
        venv = make_vec_env(cfg.env.id, run.num_envs, seed=seed, **cfg.env.args)
        info = venv.info
        net = cfg.algo.agent.build(1, info.schema())
        from learner.registry import get_algo

        kind = "softmax" if get_algo(cfg.algo_name).family == "pg" else "q"
        self.worker = RolloutWorker(
            venv, net, kind, cfg.exploration, 1, actor_id, seed, next_seq=clock_seq
        )
        host, port, token = buffer
        self.client = BufferClient(host, port, token=token, schema=info.schema(), max_retries=1000)
        # Looked up by name: a handle as a constructor argument would live in the object
        # store, which Ray cannot guarantee to a restarted actor (ray-project/ray#53727).
        self.coordinator = ray.get_actor(coordinator)
        self.metrics = ActorMetrics(actor_id) if metrics else None
        host = "127.0.0.1"
        if cfg.cluster.bind_host not in ("127.0.0.1", "localhost"):
            host = ray.util.get_node_ip_address()  # this actor's node, reachable from the head
        self.endpoint = serve(self.metrics.registry, host=host) if self.metrics else None
        # Cumulative over this process's life (`stats`): where the loop's time goes.
        self.counters = {
            "rounds": 0,
            "env_steps": 0,
            "act_s": 0.0,  # run_round: env steps and policy forward passes
            "insert_s": 0.0,  # client.insert, incl. rate-limiter waits and the fsync
            "sync_s": 0.0,  # coordinator.sync round trips and fetching new weights
            "insert_refusals": 0,  # inserts the rate limiter refused within INSERT_WAIT_S
        }

    def describe(self) -> dict:
        """pid and metrics endpoint of this actor process."""
        return {"actor_id": self.actor_id, "pid": os.getpid(), "metrics": self.endpoint}

    def stats(self) -> dict:
        """This process's loop counters (see __init__) with its pid and weights version."""
        return {**self.counters, "pid": os.getpid(), "version": self.worker.version}

    def run(self) -> dict:
        """Collect and insert until the coordinator says stop; returns this life's totals."""
        steps = episodes = 0
        total_steps = total_episodes = 0
        c = self.counters
        while True:
            started = time.perf_counter()
            _version, newer, t_env, stop = ray.get(
                self.coordinator.sync.remote(self.actor_id, self.worker.version, steps, episodes)
            )
            if stop:
                return {"env_steps": total_steps, "episodes": total_episodes}
            if newer is not None:
                weights = ray.get(newer[0])
                self.worker.set_weights(weights)
                if self.metrics:
                    self.metrics.set_weights_version(weights.version)
            acting = time.perf_counter()
            result = self.worker.run_round(t_env=t_env)
            inserting = time.perf_counter()
            self._insert(result.episodes)
            done = time.perf_counter()
            steps, episodes = result.env_steps, len(result.episodes)
            total_steps += steps
            total_episodes += episodes
            c["rounds"] += 1
            c["env_steps"] += steps
            c["sync_s"] += acting - started
            c["act_s"] += inserting - acting
            c["insert_s"] += done - inserting
            if self.metrics:
                self.metrics.record(episodes, steps)

    def _insert(self, episodes: list) -> None:
        """Insert, waiting out back-pressure (the learner is behind) for as long as it takes,
        and asking the coordinator between waits whether to stop: at the end of a run the
        loop returns within INSERT_WAIT_S instead of sitting in an insert that the service's
        shutdown would cut."""
        while True:
            try:
                self.client.insert(episodes, timeout_s=INSERT_WAIT_S)
                return
            except RateLimitedError:
                self.counters["insert_refusals"] += 1
                stop = ray.get(
                    self.coordinator.sync.remote(self.actor_id, self.worker.version, 0, 0)
                )[3]
                if stop:
                    return
