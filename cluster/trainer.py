"""The single-process training loop (`credit train --mode local`), seed-batched when asked.

One loop serves a normal run (E = 1) and a seed-batched run (E members trained side by side in
the same tensors, each with its own envs, replay and random streams; see learner.networks).
"""

from __future__ import annotations

import copy
import json
import logging
import os
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

from actors.envs.registry import make_vec_env
from actors.rollout import RolloutWorker
from buffer_service.episode import EpisodeBatch
from buffer_service.local import LocalBuffer
from cluster.config import ConfigError
from cluster.run_config import TrainConfig, data_plan
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
    """What every training loop shares: the learner, greedy evaluation, counters, checkpoints.

    Loops (`LocalTrainer` here, `cluster.cluster_trainer.ClusterTrainer`) own how episodes are
    produced and batches reach `learner.step`; they report progress through `count`.
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
        torch.set_num_threads(run.torch_threads)
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
        extra_state: Callable[[], dict] | None = None,
    ) -> None:
        """Evaluate and checkpoint when their intervals have passed."""
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
            self.save(self.checkpoint_dir, extra_state() if extra_state else {})

    def progress_text(self, records: list[EvalRecord]) -> str:
        """The greedy evaluation's figures (means over members) for a progress line."""
        text = f"test_return {np.mean([r.test_return_mean for r in records]):.2f}"
        if self.info.has_wins:
            text = f"win rate {np.mean([r.test_won_mean for r in records]):.2f} " + text
        return f"{text} updates {self.learner.updates}"

    # -- checkpoints -------------------------------------------------------------------------
    def save(self, path: Path, extra: dict | None = None) -> None:
        """Write the learner (networks, targets, optimisers, counters), loop counters, RNG
        states and the loop's `extra` state to `path` atomically: a crash mid-write leaves the
        previous checkpoint (or its `.old` copy) intact."""
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
            "test_worker_rng": self.test_worker.gen.get_state(),
            "loop": extra or {},
        }
        torch.save(state, tmp / "trainer.pt")
        (tmp / "config.yaml").write_text(yaml.safe_dump(self.cfg.to_yaml_dict(), sort_keys=False))
        old = path.with_name(path.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)

    def restore(self, path: Path) -> dict:
        """Load a checkpoint written by `save` (same config); returns the loop's extra state."""
        path = Path(path)
        if (
            not (path / "trainer.pt").exists()
            and (path.with_name(path.name + ".old") / "trainer.pt").exists()
        ):
            path = path.with_name(path.name + ".old")  # a crash between the two renames of save()
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
        return state["loop"]


class LocalTrainer:
    """Rollouts, buffer tables and updates in one process for E seed-batched members.

    Calling loop::

        trainer = LocalTrainer(cfg, n_ensemble=1)
        trainer.train(on_eval=print)       # returns when t_env reaches cfg.run.t_max
        trainer.save(path)
    """

    def __init__(self, cfg: TrainConfig, n_ensemble: int = 1, checkpoint_dir: Path | None = None):
        self.core = core = TrainerCore(cfg, n_ensemble, checkpoint_dir)
        run = cfg.run
        self.E = n_ensemble
        venv = make_vec_env(cfg.env.id, n_ensemble * run.num_envs, seed=run.seed, **cfg.env.args)
        self.worker = core.local_worker(venv, run.seed)
        self.buffers = [
            LocalBuffer(core.plan.tables, seed=run.seed * 1000 + k) for k in range(n_ensemble)
        ]
        self.update_credit = 0.0  # learner steps owed to the episodes inserted so far

    def train(
        self,
        on_eval: Callable[[list[EvalRecord]], None] | None = None,
        progress: bool = False,
        stop: Callable[[], bool] | None = None,
    ) -> None:
        """Train until t_env >= t_max (or `stop()` is true), evaluating every test_interval
        env steps."""
        core, run = self.core, self.core.cfg.run
        bar = Progress(run.t_max) if progress else None
        while core.t_env < run.t_max and not (stop and stop()):
            core.sync_worker(self.worker)
            result = self.worker.run_round(t_env=core.t_env)
            per = run.num_envs
            for k, buf in enumerate(self.buffers):
                buf.insert(result.episodes[k * per : (k + 1) * per])
            core.t_env += result.env_steps // self.E
            core.episodes += per
            # plan.updates_per_episode steps per new episode once the tables can serve a
            # batch; steps owed while they could not are dropped, not caught up (PyMARL's
            # warm-up), and a fraction carries over to the next round.
            self.update_credit += per * core.plan.updates_per_episode
            while self.update_credit >= 1.0:
                batch, extra = self._sample()
                if batch is None:
                    self.update_credit = 0.0
                    break
                self.update_credit -= 1.0
                core.update(batch, extra)
            core.periodic(on_eval, bar, self.loop_state)
        if bar:
            bar.close()

    def _sample(self) -> tuple[EpisodeBatch | None, EpisodeBatch | None]:
        """The next learner batch (and extra batch) of every member, or (None, None)."""
        plan = self.core.plan
        if not all(b.ready(plan.table, plan.batch_size) for b in self.buffers):
            return None, None
        if plan.extra_table and not all(
            b.ready(plan.extra_table, plan.extra_batch_size) for b in self.buffers
        ):
            return None, None
        batch = self._stack([b.sample(plan.table, plan.batch_size) for b in self.buffers])
        extra = None
        if plan.extra_table:
            extra = self._stack(
                [b.sample(plan.extra_table, plan.extra_batch_size) for b in self.buffers]
            )
        return batch, extra

    def _stack(self, batches: list[EpisodeBatch]) -> EpisodeBatch:
        return batches[0] if self.E == 1 else EpisodeBatch.stack(batches)

    def loop_state(self) -> dict:
        """RNG states and counters of this loop, for checkpoints. The buffer contents are not
        saved; a resumed local run refills its buffer."""
        return {
            "worker_rng": self.worker.gen.get_state(),
            "buffer_rng": [b.rng_state() for b in self.buffers],
            "episode_seq": self.worker.episode_seq,
            "update_credit": self.update_credit,
        }

    def save(self, path: Path) -> None:
        self.core.save(path, self.loop_state())

    def restore(self, path: Path) -> None:
        state = self.core.restore(path)
        self.worker.gen.set_state(state["worker_rng"])
        for buf, rng in zip(self.buffers, state["buffer_rng"], strict=True):
            buf.set_rng_state(rng)
        self.worker.episode_seq = state["episode_seq"]
        self.update_credit = state.get("update_credit", 0.0)


def write_json(path: Path, obj: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2) + "\n")
    os.replace(tmp, path)
