"""`credit train --mode cluster`: Ray rollout actors, the buffer service, and this process as
the learner. Same config, outputs and checkpoints as `--mode local`.

A launcher over the one loop (`cluster.loop.TrainLoop`, whose docstring says how the modes
behave) with the distributed sides (`cluster.launch.ray_sides`): sample a batch from the service
(the sample-to-insert limiter paces it against the actors), drop episodes older than
run.max_policy_lag, update, publish the weights (one `ray.put` per version), evaluate and
checkpoint on schedule, and restart any rollout actor loop whose process died.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from cluster.config.train import TrainConfig
from cluster.core import TrainerCore
from cluster.evaluation import EvalRecord
from cluster.launch.buffer_proc import BufferProcess
from cluster.launch.ray_sides import RayActing, ServiceData
from cluster.loop import TrainLoop, check_modes
from cluster.metrics.exporters import LearnerMetrics
from cluster.metrics.loop_stats import LoopStats
from learner.registry import ALGOS

log = logging.getLogger(__name__)


class ClusterTrainer:
    """Rollout actors on Ray, the buffer service as a child process, the learner here.

    Calling loop::

        cluster_ray.connect(address, num_cpus)      # ray.init on loopback
        cluster.process.configure(cfg.run)          # threads, seed, allocator
        trainer = ClusterTrainer(cfg, out_dir)
        trainer.restore(out_dir / "checkpoint")     # optional (--resume)
        trainer.start()
        try:
            trainer.train(on_eval=...)
        finally:
            trainer.shutdown()

    Args:
        cfg: the run.
        out: the run's folder (buffer/, checkpoint/, cluster.json, targets.json).
        n_ensemble: must be 1: several seeds in one set of tensors run only locally
            (`ConfigError` otherwise, before anything starts).
    """

    def __init__(self, cfg: TrainConfig, out: Path, n_ensemble: int = 1):
        self.cfg, self.out = cfg, Path(out)
        self.ccfg = cfg.cluster
        self.core = core = TrainerCore(
            cfg, n_ensemble, self.out / "checkpoint", actors=cfg.cluster.actors
        )
        check_modes(core.ctx, ensemble_ok=False)
        self.plan = core.ctx.plan
        self.buffer = BufferProcess(
            self.plan.tables,
            core.ctx.info.schema(),
            self.out / "buffer",
            fsync=self.ccfg.fsync,
            metrics=self.ccfg.metrics,
            host=self.ccfg.bind_host,
            seed=cfg.run.seed * 1000,  # what local mode's (first) tables sample with
            repair=self.ccfg.buffer_repair,
            store_state=self.plan.store_state,
        )
        family = ALGOS[cfg.algo_name].family
        self.metrics = (
            LearnerMetrics(algo=cfg.algo_name, family=family) if self.ccfg.metrics else None
        )
        self.stats = LoopStats()
        self.data = ServiceData(core.ctx, core.learning, self.stats, self.buffer, self.metrics)
        self.acting = RayActing(
            core.ctx, core.learning, self.out, self.buffer, self.stats, self.metrics
        )
        self.loop = TrainLoop(core, self.acting, self.data, self.stats)

    # -- what callers read -------------------------------------------------------------------
    @property
    def coordinator(self):
        return self.acting.coordinator

    @property
    def actors(self) -> list:
        return self.acting.actors

    @property
    def restarts(self) -> int:
        return self.acting.restarts

    @property
    def stop_requested(self) -> bool:
        return self.loop.stop_requested

    @stop_requested.setter
    def stop_requested(self, value: bool) -> None:
        self.loop.stop_requested = value  # set from another thread to end `train` early

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        """Start the buffer service, the coordinator and the rollout actors."""
        self.buffer.start()
        self.data.connect()
        self.acting.start(self.core.t_env, self.core.episodes)
        log.info(
            "%d rollout actors, buffer service on %s:%d",
            len(self.acting.actors),
            self.buffer.host,
            self.buffer.port,
        )

    def shutdown(self) -> None:
        """Stop the actors' loops, then the actors and the buffer service."""
        self.acting.shutdown()
        self.data.close()
        self.buffer.stop()

    def train(
        self, on_eval: Callable[[list[EvalRecord]], None] | None = None, progress: bool = False
    ) -> None:
        """Train until t_env >= run.t_max or `stop_requested` (`TrainLoop.train`)."""
        self.loop.train(on_eval, progress)

    def save(self, path: Path) -> None:
        self.loop.save(path)

    def restore(self, path: Path) -> None:
        self.loop.restore(path)
