"""What every mode's training shares: `TrainerCore`, which puts a run's parts together (its
context, learner, evaluator, checkpoints, metric means) and keeps the loop's counters and
schedule. The launchers are `cluster.launch.local` (`LocalTrainer`, seed-batched when asked)
and `cluster.launch.cluster` (`ClusterTrainer`).

The loop itself is `cluster.loop.TrainLoop` (one loop for both modes; its docstring says how
the modes behave). A seed-batched run trains E members side by side in the same tensors, each
with its own envs, replay and random streams (see learner.networks). The process-wide
settings (torch threads and seed, the allocator) are made before a trainer is built, by
`cluster.process.configure` at the entry point.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path

from buffer_service.episode import EpisodeBatch
from cluster.checkpoint import Checkpointer, global_rng_state, set_global_rng_state
from cluster.config.schema import ConfigError
from cluster.config.train import TrainConfig
from cluster.context import RunContext
from cluster.evaluation import EvalRecord, Evaluator, make_test_envs
from cluster.learning import Learning
from cluster.progress import MetricMeans, Progress
from learner.registry import Learner

BEST_FOLDER, BEST_FILE = "best", "best.json"  # run.keep_best: beside checkpoint/, and inside it


class TrainerCore:
    """A run's parts and the loop's counters: what the loop (`cluster.loop.TrainLoop`) drives.

    The parts, one job each: `ctx` (the frozen `RunContext` the sides are given), `learning`
    (the learner on its device, `Learning`), `evaluator` (greedy test episodes), `checkpointer`
    (checkpoint folders) and `means` (learner metrics between evaluations). The loop and its
    acting and data sides keep `t_env` and `episodes` current; `periodic` evaluates and
    checkpoints on their schedules.

    Args:
        cfg: the run.
        n_ensemble: seed-batched members.
        checkpoint_dir: where `periodic` checkpoints every run.save_interval (None: never);
            run.keep_best writes `best/` beside it.
        actors: rollout actors (the data plan's table sizes follow them).

    Raises:
        ConfigError: run.keep_best with n_ensemble > 1 or without a checkpoint_dir.
    """

    def __init__(
        self,
        cfg: TrainConfig,
        n_ensemble: int = 1,
        checkpoint_dir: Path | None = None,
        actors: int = 1,
    ):
        if cfg.run.keep_best and (n_ensemble != 1 or checkpoint_dir is None):
            raise ConfigError(
                f"run.keep_best needs a run of one seed that checkpoints (got n_ensemble="
                f"{n_ensemble}, checkpoint folder {checkpoint_dir}): it keeps one best policy"
            )
        venv = make_test_envs(cfg, n_ensemble)
        self.ctx = RunContext.of(cfg, venv.info, n_ensemble, actors)
        self.learning = Learning(self.ctx)
        self.evaluator = Evaluator(self.ctx, self.learning, venv)
        self.checkpointer = Checkpointer(cfg, checkpoint_dir)
        self.means = MetricMeans()
        self.t_env = 0
        self.episodes = 0
        self.last_test_t = -cfg.run.test_interval
        self.last_save_t = 0
        self.best_score: float | None = None  # run.keep_best: the best evaluation's score
        self.started = time.monotonic()
        self.wall_offset = 0.0

    @property
    def learner(self) -> Learner:
        return self.learning.learner

    @property
    def wall_s(self) -> float:
        return self.wall_offset + time.monotonic() - self.started

    def update(self, batch: EpisodeBatch, extra: EpisodeBatch | None) -> dict[str, float]:
        """One learner step, then the episode-counted target refresh; returns its metrics."""
        metrics = self.learning.update(batch, extra, self.episodes)
        self.means.record(metrics)
        return metrics

    def take_metric_means(self) -> dict[str, float]:
        """Each learner metric's mean over the updates since the previous call."""
        return self.means.take()

    def evaluate(self) -> list[EvalRecord]:
        """Greedy episodes for every member now; one record per member (with run.keep_best,
        `keep_if_best` sees it)."""
        records = self.evaluator.evaluate(self.t_env, self.episodes, self.wall_s)
        if self.ctx.run.keep_best:
            self.keep_if_best(records[0])
        return records

    def periodic(
        self,
        on_eval: Callable[[list[EvalRecord]], None] | None,
        bar: Progress | None,
        save: Callable[[Path], None] | None = None,
    ) -> None:
        """Evaluate and checkpoint when their intervals have passed.

        Args:
            on_eval: called with the evaluation's records.
            bar: the progress bar to refresh.
            save: writes a whole checkpoint to the given folder (default: `self.save`).
        """
        run, folder = self.ctx.run, self.checkpointer.folder
        if self.t_env - self.last_test_t >= run.test_interval:
            records = self.evaluate()
            self.last_test_t = self.t_env
            if on_eval:
                on_eval(records)
            if bar:
                bar.update(self.t_env, self.evaluator.progress_text(records))
        if run.save_interval and folder and self.t_env - self.last_save_t >= run.save_interval:
            self.last_save_t = self.t_env
            (save or self.save)(folder)

    # -- checkpoints -------------------------------------------------------------------------
    def keep_if_best(self, record: EvalRecord) -> bool:
        """run.keep_best: write `best/` (learner, counters, `best.json` with the evaluation)
        when `record` scores at least the best so far; a later policy wins a tie. Returns
        whether it did."""
        won = record.test_won_mean
        score = record.test_return_mean if won is None else won
        if self.best_score is not None and score < self.best_score:
            return False
        self.best_score = score
        assert self.checkpointer.folder is not None  # checked in __init__

        def evaluation(folder: Path) -> None:
            write_json(folder / BEST_FILE, record.as_json())

        self.save(self.checkpointer.folder.with_name(BEST_FOLDER), files=evaluation)
        return True

    def save(
        self, path: Path, extra: dict | None = None, files: Callable[[Path], None] | None = None
    ) -> None:
        """Write the learner (networks, targets, optimisers, counters), loop counters, RNG
        states (torch, numpy, python, the test worker's and its envs'), the learner metrics
        summed since the last evaluation and the loop's `extra` state to `path` atomically
        (`Checkpointer.write`).

        Args:
            path: the checkpoint folder.
            extra: the loop's own state (RNG states, counters).
            files: writes more files into the folder being built (e.g. buffer tables).
        """
        state = {
            "t_env": self.t_env,
            "episodes": self.episodes,
            "last_test_t": self.last_test_t,
            "last_save_t": self.last_save_t,
            "wall_s": self.wall_s,
            "best_score": self.best_score,
            **global_rng_state(),
            **self.evaluator.state(),
            "metric_sums": self.means.state(),
            "loop": extra or {},
        }
        self.checkpointer.write(path, self.learner.state_dict(), state, files)

    def restore(self, path: Path) -> dict:
        """Load a checkpoint written by `save` (same config); returns the loop's extra state."""
        learner_state, state = self.checkpointer.read(path)
        self.learner.load_state_dict(learner_state)
        self.t_env, self.episodes = state["t_env"], state["episodes"]
        self.last_test_t, self.last_save_t = state["last_test_t"], state["last_save_t"]
        self.wall_offset = state["wall_s"]
        self.best_score = state.get("best_score")  # absent from checkpoints of earlier commits
        self.started = time.monotonic()
        set_global_rng_state(state)
        self.evaluator.load_state(state)
        if "metric_sums" in state:  # absent from checkpoints of earlier commits
            self.means.load_state(state["metric_sums"])
        return state["loop"]


def write_json(path: Path, obj: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2) + "\n")
    os.replace(tmp, path)
