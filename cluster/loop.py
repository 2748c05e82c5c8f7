"""The one training loop, for `--mode local` and `--mode cluster` alike.

`TrainLoop` drives a `TrainerCore` (learner, evaluation, checkpoints, counters) against two
small interfaces, the acting side (`ActingSide`: an in-process `RolloutWorker`,
`cluster.launch.local.LocalActing`, or Ray rollout actors, `cluster.launch.ray_sides.RayActing`) and
the data side (`DataSide`: in-process buffer tables, `cluster.launch.local.LocalData`, or the
buffer service over TCP, `cluster.launch.ray_sides.ServiceData`). `LocalTrainer` and
`ClusterTrainer` only choose the pair. The sides are given the run's frozen context
(`cluster.context.RunContext`) and the learner (`cluster.learning.Learning`), never the core.

Behaviour of the two modes (the one place it is written down)
--------------------------------------------------------------
* Tables and their limits: both modes use the tables of `cluster.config.plan.data_plan` with
  the same `buffer_service.tables.Table` code, sample-to-insert limiter included, sampling with or
  without replacement as `replay.with_replacement` says.
* Pacing (`replay.updates_per_episode`, the policy-gradient tables' reuse): the learner takes
  its batches only when the tables' limiters allow a sample, in both modes. Local mode acts
  and learns in turn, so it also takes exactly the updates owed to the episodes of each round
  (steps owed while the tables could not serve a batch are dropped: the warm-up). An insert
  the limiter holds back waits for the learner in both modes: a Ray actor waits in its
  insert; local mode first takes the updates the limiter allows, and stops with
  `RateLimitDeadlockError` if none is possible (the configuration would hang in cluster mode too).
* Episode validation: every inserted episode is checked against the env's schema
  (`Episode.validate`) by the buffer service and by the local tables alike.
* Seeds: actor k's envs and action sampling are seeded with `messages.actor_seed(run.seed, k)`
  (no wall clock); the local worker is actor 0, so local mode and a one-actor cluster run
  act alike until their learners' timing differs. The local tables sample with seed
  `run.seed * 1000 + member`, the buffer service with `run.seed * 1000`.
* `run.max_policy_lag`: sampled episodes more than that many versions behind the learner are
  dropped before the update, in both modes (a batch left empty is no batch). With several
  seeds in one set of tensors it is refused (`ConfigError`): members' batches must stack.
* Several seeds in one set of tensors (`n_ensemble` > 1): local mode only; `ClusterTrainer`
  refuses it with a `ConfigError` naming `n_ensemble`.
* Resume: cluster mode keeps the buffer service's durable log and snapshots
  (`OUT/buffer/data`); local mode writes its tables into every checkpoint, in the same
  snapshot format (`checkpoint/buffer/member-k`, readable by `credit buffer verify`), and
  restores them, so a resumed local run continues with the replay it had, exactly as if it
  had not stopped: the checkpoint also holds every random state (torch, numpy, python, the
  workers', the replay's sampling and the envs' own where they offer one,
  `actors.envs.base.rng_state`; skirmish and matrix games do). Each checkpoint writes the whole
  tables, so mind run.save_interval with a large replay.capacity.
* Typed messages: what crosses a process boundary is a frozen dataclass of
  `cluster.messages`; an actor receives only its `ActorConfig`, whose acting network is the
  learner's description of it (`Learner.acting`, `learner.networks.ActingSpec`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Protocol

from buffer_service.episode import Episode, EpisodeBatch
from cluster import process
from cluster.checkpoint import checkpoint_folder
from cluster.config.schema import ConfigError
from cluster.context import RunContext
from cluster.core import TrainerCore
from cluster.evaluation import EvalRecord
from cluster.metrics.loop_stats import LoopStats
from cluster.progress import Progress
from learner.timers import TIMERS, timed

log = logging.getLogger(__name__)

Pair = tuple[EpisodeBatch, EpisodeBatch | None]


class RateLimitDeadlockError(RuntimeError):
    """A local insert that the rate limiter holds back while no batch can be sampled: the
    same configuration would block its actors and its learner forever in cluster mode."""


class ActingSide(Protocol):
    """Where episodes come from.

    Calling loop (`TrainLoop.train`)::

        steps, episodes = acting.act(t_env, episodes)  # new since the loop's totals so far
        ...learner updates...
        acting.updated(seconds, metrics)   # after each update (publish weights, metrics)
        acting.evaluated(records)          # after each greedy evaluation
    """

    def act(self, t_env: int, episodes: int) -> tuple[int, int]: ...
    def updated(self, seconds: float, metrics: dict[str, float]) -> None: ...
    def evaluated(self, records: list[EvalRecord]) -> None: ...
    def state(self) -> dict[str, Any]: ...
    def load_state(self, state: dict[str, Any]) -> None: ...


class DataSide(Protocol):
    """Where batches come from.

    Calling loop (`TrainLoop.train`)::

        for batch, extra in data.catch_up():      # before acting: what an insert waits for
            learner.step(batch, extra)
        for batch, extra in data.batches(new_episodes):
            learner.step(batch, extra)
        data.write(tmp_checkpoint_folder)         # with every checkpoint
    """

    def catch_up(self) -> Iterator[Pair]: ...
    def batches(self, new_episodes: int) -> Iterator[Pair]: ...
    def write(self, folder: Path) -> None: ...
    def read(self, folder: Path) -> None: ...
    def state(self) -> dict[str, Any]: ...
    def load_state(self, state: dict[str, Any]) -> None: ...


def check_modes(ctx: RunContext, ensemble_ok: bool) -> None:
    """Refuse what a mode cannot do, naming the key (see the module docstring).

    Args:
        ctx: the run (its n_ensemble, its config).
        ensemble_ok: whether the acting side can hold several seeds in one set of tensors.
    Raises:
        ConfigError: n_ensemble > 1 where the acting side cannot, or run.max_policy_lag
            with n_ensemble > 1.
    """
    n, lag = ctx.n_ensemble, ctx.run.max_policy_lag
    if n > 1 and not ensemble_ok:
        raise ConfigError(
            f"n_ensemble={n}: several seeds in one set of tensors run only in "
            "--mode local; in cluster mode run one seed per run (n_ensemble=1)"
        )
    if n > 1 and lag:
        raise ConfigError(
            f"run.max_policy_lag={lag} needs n_ensemble=1 (got {n}): dropping stale "
            "episodes would give the members batches of different sizes"
        )


def drop_stale(
    episodes: list[Episode], version: int, limit: int, stats: LoopStats
) -> tuple[list[Episode], list[int]]:
    """Count the policy lag of sampled episodes and keep those within `limit` versions.

    Args:
        episodes: a sampled batch's episodes.
        version: the learner's current weights version (its update count).
        limit: run.max_policy_lag (0 keeps every episode).
        stats: where the lags are counted (`lag_counts`, `dropped_stale`).
    Returns:
        (the episodes kept, every sampled episode's lag clipped at 0).
    """
    lags = [max(0, version - ep.policy_version) for ep in episodes]
    stats.lag_counts.update(lags)
    if not limit:
        return episodes, lags
    fresh = [ep for ep, lag in zip(episodes, lags, strict=True) if lag <= limit]
    stats.dropped_stale += len(episodes) - len(fresh)
    return fresh, lags


class TrainLoop:
    """Act, insert, update, publish, evaluate, checkpoint: one loop for both modes.

    Calling loop::

        loop = TrainLoop(core, acting, data)
        loop.restore(path)                    # optional: a checkpoint written by `save`
        loop.train(on_eval=print)             # until t_env >= run.t_max or `stop()`
        loop.save(path)

    Args:
        core: the learner, evaluation, counters and checkpoints.
        acting: the acting side.
        data: the data side.
        stats: the loop's counters (shared with the data side, which counts its samples).
    """

    def __init__(
        self, core: TrainerCore, acting: ActingSide, data: DataSide, stats: LoopStats
    ) -> None:
        self.core, self.acting, self.data, self.stats = core, acting, data, stats
        self.stop_requested = False  # may be set from another thread to end `train` early
        # more files for every checkpoint: each is called with the folder being written
        # (before it replaces the previous checkpoint), e.g. a repro pair's evaluation log
        self.checkpoint_files: list[Callable[[Path], None]] = []

    def train(
        self,
        on_eval: Callable[[list[EvalRecord]], None] | None = None,
        progress: bool = False,
        stop: Callable[[], bool] | None = None,
    ) -> None:
        """Train until t_env >= run.t_max (or `stop()` is true, or `stop_requested`),
        evaluating every run.test_interval env steps and checkpointing every
        run.save_interval.

        Args:
            on_eval: called with each evaluation's records (one per ensemble member).
            progress: show a progress bar (a log line when stderr is not a terminal).
            stop: polled once per iteration.
        """
        core, run = self.core, self.core.ctx.run
        bar = Progress(run.t_max) if progress else None

        def evaluated(records: list[EvalRecord]) -> None:
            self.acting.evaluated(records)
            if on_eval:
                on_eval(records)

        while core.t_env < run.t_max and not self.stop_requested and not (stop and stop()):
            for pair in TIMERS.iterate("sample", self.data.catch_up()):
                self._update(pair)
            with timed("act"):
                steps, episodes = self.acting.act(core.t_env, core.episodes)
            core.t_env += steps
            core.episodes += episodes
            for pair in TIMERS.iterate("sample", self.data.batches(episodes)):
                self._update(pair)
            with timed("periodic"):  # evaluation, and the checkpoint ("periodic/checkpoint")
                core.periodic(evaluated, bar, self._timed_save)
            process.tick()  # run.torch_threads "auto": the free CPUs, measured again
        if bar:
            bar.close()

    def _update(self, pair: Pair) -> None:
        batch, extra = pair
        started = time.perf_counter()
        with timed("update"):
            metrics = self.core.update(batch, extra)
        seconds = time.perf_counter() - started
        self.stats.updates += 1
        self.stats.update_s += seconds
        self.stats.consumed_env_steps += int(batch.filled.sum())
        self.acting.updated(seconds, metrics)

    # -- checkpoints -------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """The acting and data sides' counters and RNG states, for a checkpoint."""
        return {**self.acting.state(), **self.data.state()}

    def _timed_save(self, path: Path) -> None:
        with timed("checkpoint"):
            self.save(path)

    def save(self, path: Path, replay: bool = True) -> None:
        """Checkpoint the learner, the loop and (local mode, with `replay`) the buffer tables
        to `path`. Without them the checkpoint holds the networks, optimisers and counters
        only (a resumed run refills its replay)."""

        def files(folder: Path) -> None:
            if replay:
                self.data.write(folder)
            for write in self.checkpoint_files:
                write(folder)

        self.core.save(path, self.state(), files=files)

    def restore(self, path: Path) -> None:
        """Continue from a checkpoint written by `save`."""
        state = self.core.restore(path)
        self.acting.load_state(state)
        self.data.load_state(state)
        self.data.read(checkpoint_folder(path))
