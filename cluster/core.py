"""What every mode's training shares (`TrainerCore`: learner, evaluation, checkpoints, the
evaluation records and the progress line). The launchers are `cluster.launch.local`
(`LocalTrainer`, seed-batched when asked) and `cluster.launch.cluster` (`ClusterTrainer`).

The loop itself is `cluster.loop.TrainLoop` (one loop for both modes; its docstring says how
the modes behave). A seed-batched run trains E members side by side in the same tensors, each
with its own envs, replay and random streams (see learner.networks).
"""

from __future__ import annotations

import copy
import json
import logging
import os
import random
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

from actors.envs.base import rng_state, set_rng_state
from actors.envs.registry import make_vec_env
from actors.rollout import RolloutWorker
from buffer_service.episode import EpisodeBatch
from cluster.alloc import keep_freed_memory
from cluster.config.plan import data_plan
from cluster.config.schema import ConfigError
from cluster.config.train import TrainConfig
from cluster.cpu import ThreadGovernor
from learner.precision import autocast, effective_precision
from learner.registry import Learner, get_algo

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvalRecord:
    """One greedy evaluation of one ensemble member."""

    member: int
    t_env: int
    episode: int
    test_return_mean: float
    test_won_mean: float | None
    wall_s: float
    updates: int

    def as_json(self) -> dict:
        d = {
            "t_env": self.t_env,
            "episode": self.episode,
            "test_return_mean": self.test_return_mean,
            "wall_s": round(self.wall_s, 3),
            "updates": self.updates,
        }
        if self.test_won_mean is not None:
            d["test_won_mean"] = self.test_won_mean
        return d


class Progress:
    """A one-line progress bar on a terminal, log lines otherwise (at most one per `every_s`),
    each with the env steps per second between the last two changes of the step count (a
    caller that learns the count only at evaluations, as `credit repro` does, keeps showing
    the last measured rate instead of 0)."""

    def __init__(self, total: int, every_s: float = 5.0):
        self.total, self.every_s = total, every_s
        self.tty = sys.stderr.isatty()
        self.last = 0.0
        self.changed: tuple[int, float] | None = None  # (done, monotonic time) of the last change
        self.rate = ""

    def update(self, done: int, text: str) -> None:
        now = time.monotonic()
        if self.changed is None:
            self.changed = (done, now)
        elif done != self.changed[0] and now > self.changed[1]:
            per_s = (done - self.changed[0]) / (now - self.changed[1])
            self.rate = f" | {per_s:,.0f} env steps/s"
            self.changed = (done, now)
        if self.tty:
            frac = min(1.0, done / self.total)
            bar = "#" * int(30 * frac)
            sys.stderr.write(
                f"\r[{bar:<30}] {100 * frac:5.1f}% t_env {done:,} {text}{self.rate}\x1b[K"
            )
            sys.stderr.flush()
        elif now - self.last >= self.every_s:
            log.info("t_env %d/%d %s%s", done, self.total, text, self.rate)
            self.last = now

    def close(self) -> None:
        if self.tty:
            sys.stderr.write("\n")


class TrainerCore:
    """What the training loop shares between modes: the learner, greedy evaluation, counters,
    checkpoints.

    The loop (`cluster.loop.TrainLoop`) and its acting and data sides own how episodes are
    produced and how batches reach `learner.step` (through `update`); they keep `t_env` and
    `episodes` current.
    """

    def __init__(
        self,
        cfg: TrainConfig,
        n_ensemble: int = 1,
        checkpoint_dir: Path | None = None,
        actors: int = 1,
    ):
        self.cfg, self.E = cfg, n_ensemble
        self.checkpoint_dir = checkpoint_dir
        run = cfg.run
        self.threads = ThreadGovernor(run.torch_threads)
        if run.keep_freed_memory:
            keep_freed_memory()
        torch.manual_seed(run.seed)
        self.spec = get_algo(cfg.algo_name)
        self.plan = data_plan(cfg, actors)
        self.test_venv = make_vec_env(
            cfg.env.id, n_ensemble * run.test_episodes, seed=run.seed + 10_000, **cfg.env.args
        )
        self.info = self.test_venv.info
        device = torch.device(run.device)
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ConfigError(
                f"run.device={run.device!r}, but this torch sees no CUDA device "
                f"(torch {torch.__version__}, cuda available: False); use run.device=cpu"
            )
        self.learner: Learner = self.spec.build(
            cfg.algo, self.info.schema(), n_ensemble, run.device
        )
        self.device, self.precision = device, effective_precision(run.precision, device)
        mode = run.acting_weights
        if mode == "auto":
            mode = "shared" if device.type == "cpu" else "copy"
        self.acting_weights = mode
        self.test_worker = self.local_worker(self.test_venv, run.seed + 1)
        self.t_env = 0
        self.episodes = 0
        self.last_test_t = -run.test_interval
        self.last_save_t = 0
        self.started = time.monotonic()
        self.wall_offset = 0.0
        self.last_metrics: dict[str, float] = {}  # the latest update's learner metrics
        self._metric_sums: dict[str, list[float]] = {}  # key -> [sum, count] since `take`

    def record_update(self, metrics: dict[str, float]) -> None:
        """Keep one update's learner metrics: as the latest, and in the running means that
        `take_metric_means` hands out."""
        self.last_metrics = metrics
        for k, v in metrics.items():
            acc = self._metric_sums.setdefault(k, [0.0, 0])
            acc[0] += float(v)
            acc[1] += 1

    def update(self, batch: EpisodeBatch, extra: EpisodeBatch | None) -> dict[str, float]:
        """One learner step, then the episode-counted target refresh; returns its metrics."""
        with autocast(self.precision, self.device):
            metrics = self.learner.step(batch, extra)
        self.learner.sync_targets(self.episodes)
        self.record_update(metrics)
        return metrics

    def take_metric_means(self) -> dict[str, float]:
        """Each learner metric's mean over the updates since the previous call."""
        means = {k: total / n for k, (total, n) in self._metric_sums.items()}
        self._metric_sums = {}
        return means

    def local_worker(self, venv, seed: int, actor_id: int = 0) -> RolloutWorker:
        """A worker in this process: acting with the learner's own agent module
        (acting_weights "shared") or with a CPU copy of it ("copy"); `sync_worker` before each
        round keeps its weights and policy_version tags current."""
        agent = self.learner.agent
        if self.acting_weights == "copy":
            # deepcopy, not a fresh build: building would draw from torch's global RNG.
            agent = copy.deepcopy(agent).to("cpu").requires_grad_(False)
        return RolloutWorker(
            venv, agent, self.learner.policy_kind, self.cfg.exploration, self.E, actor_id, seed
        )

    def sync_worker(self, worker: RolloutWorker) -> None:
        """Bring a `local_worker` to the learner's current version: a shared module only needs
        the version tag; a copy loads the learner's weights (CPU numpy arrays) when newer."""
        if self.acting_weights == "shared":
            worker.follow(self.learner.updates)
        elif self.learner.updates > worker.version:
            worker.set_weights(self.learner.get_weights())

    @property
    def wall_s(self) -> float:
        return self.wall_offset + time.monotonic() - self.started

    def evaluate(self) -> list[EvalRecord]:
        """Greedy episodes for every member; one record per member."""
        self.sync_worker(self.test_worker)
        result = self.test_worker.run_round(t_env=self.t_env, greedy=True)
        per = self.cfg.run.test_episodes
        has_wins = self.info.has_wins
        records = []
        for k in range(self.E):
            sl = slice(k * per, (k + 1) * per)
            records.append(
                EvalRecord(
                    member=k,
                    t_env=self.t_env,
                    episode=self.episodes,
                    test_return_mean=float(result.returns[sl].mean()),
                    test_won_mean=float(result.won[sl].mean()) if has_wins else None,
                    wall_s=self.wall_s,
                    updates=self.learner.updates,
                )
            )
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
        run = self.cfg.run
        if self.t_env - self.last_test_t >= run.test_interval:
            records = self.evaluate()
            self.last_test_t = self.t_env
            if on_eval:
                on_eval(records)
            if bar:
                bar.update(self.t_env, self.progress_text(records))
        if (
            run.save_interval
            and self.checkpoint_dir
            and self.t_env - self.last_save_t >= run.save_interval
        ):
            self.last_save_t = self.t_env
            (save or self.save)(self.checkpoint_dir)

    def progress_text(self, records: list[EvalRecord]) -> str:
        """The greedy evaluation's figures (means over members) for a progress line."""
        text = f"test_return {np.mean([r.test_return_mean for r in records]):.2f}"
        if self.info.has_wins:
            text = f"win rate {np.mean([r.test_won_mean for r in records]):.2f} " + text
        return f"{text} updates {self.learner.updates}"

    # -- checkpoints -------------------------------------------------------------------------
    def save(
        self, path: Path, extra: dict | None = None, files: Callable[[Path], None] | None = None
    ) -> None:
        """Write the learner (networks, targets, optimisers, counters), loop counters, RNG
        states (torch, numpy, python, the test worker's and its envs'), the learner metrics
        summed since the last evaluation and the loop's `extra` state to `path` atomically:
        a crash mid-write leaves the previous checkpoint (or its `.old` copy) intact.

        Args:
            path: the checkpoint folder.
            extra: the loop's own state (RNG states, counters).
            files: writes more files into the folder being built (e.g. buffer tables).
        """
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        torch.save(self.learner.state_dict(), tmp / "learner.pt")
        state = {
            "t_env": self.t_env,
            "episodes": self.episodes,
            "last_test_t": self.last_test_t,
            "last_save_t": self.last_save_t,
            "wall_s": self.wall_s,
            "torch_rng": torch.get_rng_state(),
            "numpy_rng": np.random.get_state(),
            "python_rng": random.getstate(),
            "test_worker_rng": self.test_worker.gen.get_state(),
            "test_env_rng": rng_state(self.test_venv),
            "metric_sums": copy.deepcopy(self._metric_sums),
            "loop": extra or {},
        }
        torch.save(state, tmp / "trainer.pt")
        (tmp / "config.yaml").write_text(yaml.safe_dump(self.cfg.to_yaml_dict(), sort_keys=False))
        if files:
            files(tmp)
        old = path.with_name(path.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)

    @staticmethod
    def checkpoint_folder(path: Path) -> Path:
        """The folder holding the checkpoint `save` wrote to `path`: `path`, or its `.old`
        copy after a crash between the two renames of `save`."""
        path = Path(path)
        old = path.with_name(path.name + ".old")
        if not (path / "trainer.pt").exists() and (old / "trainer.pt").exists():
            return old
        return path

    def restore(self, path: Path) -> dict:
        """Load a checkpoint written by `save` (same config); returns the loop's extra state."""
        path = self.checkpoint_folder(path)
        device = self.cfg.run.device  # a checkpoint saved on another device loads here
        learner_state = torch.load(path / "learner.pt", weights_only=False, map_location=device)
        self.learner.load_state_dict(learner_state)
        state = torch.load(path / "trainer.pt", weights_only=False, map_location="cpu")
        self.t_env, self.episodes = state["t_env"], state["episodes"]
        self.last_test_t, self.last_save_t = state["last_test_t"], state["last_save_t"]
        self.wall_offset = state["wall_s"]
        self.started = time.monotonic()
        torch.set_rng_state(state["torch_rng"])
        self.test_worker.gen.set_state(state["test_worker_rng"])
        if "numpy_rng" in state:  # absent from checkpoints of earlier commits
            np.random.set_state(state["numpy_rng"])
            random.setstate(state["python_rng"])
            set_rng_state(self.test_venv, state["test_env_rng"])
            self._metric_sums = state["metric_sums"]
        return state["loop"]


def write_json(path: Path, obj: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2) + "\n")
    os.replace(tmp, path)
