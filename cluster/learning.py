"""The learner of a run on its device (`Learning`): built from the run's context, stepped by
the loop, and followed by the workers that act in the learner's own process."""

from __future__ import annotations

import copy

import torch

from actors.rollout import RolloutWorker
from buffer_service.episode import EpisodeBatch
from cluster.config.schema import ConfigError
from cluster.context import RunContext
from learner.precision import autocast, effective_precision
from learner.registry import Learner


class Learning:
    """The run's learner, its device and precision, and how in-process workers act with it.

    Args:
        ctx: the run.
    Raises:
        ConfigError: run.device names CUDA and this torch sees none.
    """

    def __init__(self, ctx: RunContext) -> None:
        self.ctx, run = ctx, ctx.cfg.run
        device = torch.device(run.device)
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ConfigError(
                f"run.device={run.device!r}, but this torch sees no CUDA device "
                f"(torch {torch.__version__}, cuda available: False); use run.device=cpu"
            )
        self.learner: Learner = ctx.spec.build(
            ctx.cfg.algo, ctx.info.schema(), ctx.n_ensemble, run.device
        )
        self.device, self.precision = device, effective_precision(run.precision, device)
        mode = run.acting_weights
        if mode == "auto":
            mode = "shared" if device.type == "cpu" else "copy"
        self.acting_weights = mode

    @property
    def version(self) -> int:
        """The learner's weights version (its update count)."""
        return self.learner.updates

    def update(self, batch: EpisodeBatch, extra: EpisodeBatch | None, episodes: int) -> dict:
        """One learner step, then the target refresh counted in `episodes` (the loop's total);
        returns the step's metrics."""
        with autocast(self.precision, self.device):
            metrics = self.learner.step(batch, extra)
        self.learner.sync_targets(episodes)
        return metrics

    def local_worker(self, venv, seed: int, actor_id: int = 0) -> RolloutWorker:
        """A worker in this process: acting with the learner's own agent module
        (acting_weights "shared") or with a CPU copy of it ("copy"); `sync_worker` before each
        round keeps its weights and policy_version tags current."""
        agent = self.learner.agent
        if self.acting_weights == "copy":
            # deepcopy, not a fresh build: building would draw from torch's global RNG.
            agent = copy.deepcopy(agent).to("cpu").requires_grad_(False)
        ctx = self.ctx
        return RolloutWorker(
            venv,
            agent,
            self.learner.policy_kind,
            ctx.cfg.exploration,
            ctx.n_ensemble,
            actor_id,
            seed,
        )

    def sync_worker(self, worker: RolloutWorker) -> None:
        """Bring a `local_worker` to the learner's current version: a shared module only needs
        the version tag; a copy loads the learner's weights (CPU numpy arrays) when newer."""
        if self.acting_weights == "shared":
            worker.follow(self.learner.updates)
        elif self.learner.updates > worker.version:
            worker.set_weights(self.learner.get_weights())
