"""What a run is, fixed before it starts (`RunContext`): handed to the loop's sides instead of
the trainer, so they read the run's settings and never its moving parts."""

from __future__ import annotations

from dataclasses import dataclass

from actors.envs.base import EnvInfo
from cluster.config.plan import DataPlan, data_plan
from cluster.config.train import RunConfig, TrainConfig
from learner.registry import AlgoSpec, get_algo


@dataclass(frozen=True)
class RunContext:
    """A run's configuration and what follows from it.

    Attributes:
        cfg: the resolved configuration.
        spec: the algorithm's registry entry.
        info: the env's shapes and whether it reports wins.
        plan: the buffer tables and the learner's batches (`cluster.config.plan`).
        n_ensemble: seed-batched members trained in one set of tensors.
    """

    cfg: TrainConfig
    spec: AlgoSpec
    info: EnvInfo
    plan: DataPlan
    n_ensemble: int

    @property
    def run(self) -> RunConfig:
        return self.cfg.run

    @classmethod
    def of(cls, cfg: TrainConfig, info: EnvInfo, n_ensemble: int, actors: int) -> RunContext:
        """The context of `cfg` with `actors` rollout actors, in an env described by `info`."""
        return cls(cfg, get_algo(cfg.algo_name), info, data_plan(cfg, actors), n_ensemble)
