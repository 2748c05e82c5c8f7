"""`--mode local`: the launcher `LocalTrainer` and the in-process sides of
`cluster.loop.TrainLoop` it runs with, one `RolloutWorker` (actor 0) and one set of buffer
tables per ensemble member."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from actors.envs.base import rng_state, set_rng_state
from actors.envs.registry import make_vec_env
from actors.rollout import RolloutWorker
from buffer_service.episode import EpisodeBatch
from buffer_service.local import LocalBuffer
from cluster.batches import BatchPairer
from cluster.config.train import TrainConfig
from cluster.context import RunContext
from cluster.core import TrainerCore
from cluster.evaluation import EvalRecord
from cluster.learning import Learning
from cluster.loop import Pair, RateLimitDeadlockError, TrainLoop, check_modes, drop_stale
from cluster.messages import actor_seed
from cluster.metrics.loop_stats import LoopStats

log = logging.getLogger(__name__)

BUFFER_FOLDER = "buffer"  # in a checkpoint: buffer/member-<k>, one snapshot folder each


class LocalData:
    """E members' buffer tables in this process (`buffer_service.local.LocalBuffer`).

    Args:
        ctx: the run (its data plan, seed, schema).
        learning: the learner (its version, for run.max_policy_lag).
        stats: the loop's counters.
    """

    def __init__(self, ctx: RunContext, learning: Learning, stats: LoopStats) -> None:
        self.ctx, self.learning, self.stats, self.plan = ctx, learning, stats, ctx.plan
        seed, schema = ctx.run.seed, ctx.info.schema()
        self.buffers = [
            LocalBuffer(
                self.plan.tables, seed * 1000 + k, schema, store_state=self.plan.store_state
            )
            for k in range(ctx.n_ensemble)
        ]
        self.update_credit = 0.0  # learner steps owed to the episodes inserted so far
        self.pairer = BatchPairer(self.plan, self._take, self._ready)

    def insert(self, episodes: list, per_member: int) -> None:
        """Member k's episodes are episodes[k * per_member : (k + 1) * per_member]."""
        for k, buf in enumerate(self.buffers):
            buf.insert(episodes[k * per_member : (k + 1) * per_member])

    def catch_up(self) -> Iterator[Pair]:
        """The batches the rate limiter needs sampled before it lets the next insert in (what
        a Ray actor's insert waits for); raises RateLimitDeadlockError when none can be sampled."""
        while not all(b.can_insert() for b in self.buffers):
            pair = self.sample()
            if pair is None:
                raise RateLimitDeadlockError(
                    "the rate limiter holds back the next insert, but no batch can be sampled "
                    f"(tables {[t.name for t in self.plan.tables]}: "
                    f"{self.buffers[0].stats()['tables']}); check the tables' "
                    "sizes and batch sizes (replay.*, cycling.*, run.num_envs)"
                )
            yield pair

    def batches(self, new_episodes: int) -> Iterator[Pair]:
        """plan.updates_per_episode batches per new episode (of one member) once the tables
        can serve one; steps owed while they could not are dropped, not caught up (PyMARL's
        warm-up), and a fraction carries over to the next round."""
        self.update_credit += new_episodes * self.plan.updates_per_episode
        while self.update_credit >= 1.0:
            pair = self.sample()
            if pair is None:
                self.update_credit = 0.0
                return
            self.update_credit -= 1.0
            yield pair

    def sample(self) -> Pair | None:
        """The next learner batch (and extra batch) of every member, or None: the one
        `BatchPairer` of both modes, sampling only once every member's tables can serve."""
        return self.pairer.next()

    def _ready(self, table: str, n: int) -> bool:
        return all(b.ready(table, n) for b in self.buffers)

    def _take(self, table: str, n: int) -> EpisodeBatch | None:
        limit, version = self.ctx.run.max_policy_lag, self.learning.version
        self.stats.sample_requests += len(self.buffers)
        members = []
        for buf in self.buffers:
            episodes, _ = drop_stale(buf.sample_episodes(table, n), version, limit, self.stats)
            if not episodes:
                return None
            members.append(episodes)
        if len(members) == 1:
            return EpisodeBatch.from_episodes(members[0])
        return EpisodeBatch.from_members(members)

    def write(self, folder: Path) -> None:
        for k, buf in enumerate(self.buffers):
            buf.write(Path(folder) / BUFFER_FOLDER / f"member-{k}")

    def read(self, folder: Path) -> None:
        root = Path(folder) / BUFFER_FOLDER
        if not root.is_dir():
            log.warning("checkpoint %s holds no buffer tables (an older format); refilling", folder)
            return
        for k, buf in enumerate(self.buffers):
            buf.read(root / f"member-{k}")

    def state(self) -> dict[str, Any]:
        return {
            "buffer_rng": [b.rng_state() for b in self.buffers],
            "update_credit": self.update_credit,
            "dropped_stale": self.stats.dropped_stale,
        }

    def load_state(self, state: dict[str, Any]) -> None:
        for buf, rng in zip(self.buffers, state["buffer_rng"], strict=True):
            buf.set_rng_state(rng)
        self.update_credit = state.get("update_credit", 0.0)
        self.stats.dropped_stale = state.get("dropped_stale", 0)


class LocalActing:
    """Actor 0 in this process: `run.num_envs` envs per member, acting with the learner's
    network (or a CPU copy, run.acting_weights), inserting each round into `data`.

    Args:
        ctx: the run.
        learning: the learner the worker acts with.
        data: where the rounds go.
    """

    def __init__(self, ctx: RunContext, learning: Learning, data: LocalData) -> None:
        self.ctx, self.learning, self.data = ctx, learning, data
        env, run = ctx.cfg.env, ctx.run
        seed = actor_seed(run.seed, 0)
        venv = make_vec_env(env.id, ctx.n_ensemble * run.num_envs, seed=seed, **env.args)
        self.worker = learning.local_worker(venv, seed)

    def act(self, t_env: int, episodes: int) -> tuple[int, int]:
        """One round of every env at the loop's `t_env`, inserted; returns (env steps per
        member, episodes per member)."""
        per = self.ctx.run.num_envs
        self.learning.sync_worker(self.worker)
        result = self.worker.run_round(t_env=t_env)
        self.data.insert(result.episodes, per)
        return result.env_steps // self.ctx.n_ensemble, per

    def updated(self, seconds: float, metrics: dict[str, float]) -> None:
        """Nothing to publish: the worker syncs with the learner before each round."""

    def evaluated(self, records: list[EvalRecord]) -> None:
        """No exporters in local mode."""

    def state(self) -> dict[str, Any]:
        return {
            "worker_rng": self.worker.gen.get_state(),
            "episode_seq": self.worker.episode_seq,
            "env_rng": rng_state(self.worker.venv),
        }

    def load_state(self, state: dict[str, Any]) -> None:
        self.worker.gen.set_state(state["worker_rng"])
        self.worker.episode_seq = state["episode_seq"]
        set_rng_state(self.worker.venv, state.get("env_rng"))


class LocalTrainer:
    """`--mode local`: the one loop (`cluster.loop.TrainLoop`) with an in-process worker and
    in-process buffer tables, for E seed-batched members.

    Calling loop::

        cluster.process.configure(cfg.run) # at the entry point: threads, seed, allocator
        trainer = LocalTrainer(cfg, n_ensemble=1)
        trainer.train(on_eval=print)       # returns when t_env reaches cfg.run.t_max
        trainer.save(path)
    """

    def __init__(self, cfg: TrainConfig, n_ensemble: int = 1, checkpoint_dir: Path | None = None):
        self.core = core = TrainerCore(cfg, n_ensemble, checkpoint_dir)
        check_modes(core.ctx, ensemble_ok=True)
        self.E = n_ensemble
        self.stats = LoopStats()
        self.data = LocalData(core.ctx, core.learning, self.stats)
        self.acting = LocalActing(core.ctx, core.learning, self.data)
        self.loop = TrainLoop(core, self.acting, self.data, self.stats)

    @property
    def worker(self) -> RolloutWorker:
        """The in-process rollout worker."""
        return self.acting.worker

    def train(
        self,
        on_eval: Callable[[list[EvalRecord]], None] | None = None,
        progress: bool = False,
        stop: Callable[[], bool] | None = None,
    ) -> None:
        """Train until t_env >= t_max (or `stop()` is true), evaluating every test_interval
        env steps (`TrainLoop.train`)."""
        self.loop.train(on_eval, progress, stop)

    def save(self, path: Path, replay: bool = True) -> None:
        self.loop.save(path, replay)

    def restore(self, path: Path) -> None:
        self.loop.restore(path)
