"""The one explicit algorithm registry: name -> (Config, learner factory).

Tests iterate `ALGOS`; nothing registers itself on import.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from buffer_service.episode import EpisodeBatch, EpisodeSchema
from learner.coma import COMAConfig, COMALearner
from learner.networks import ActingSpec, AgentNet, VersionedWeights
from learner.pg import CACConfig, CACLearner
from learner.rdn import RDNConfig, RDNLearner
from learner.value import ValueConfig, ValueLearner


class Learner(Protocol):
    """What the trainer needs of an algorithm.

    Calling loop::

        learner = ALGOS[name].build(cfg, schema, n_ensemble, "cpu")
        for batch in batches:
            metrics = learner.step(batch)       # dict of scalar losses and diagnostics
            # (extended policy-gradient learners also take `extra`, an off-policy batch)
            learner.sync_targets(episodes)      # total inserted episodes: target refresh
        net = learner.acting.build()            # an actor's own acting network
        actors.set_weights(learner.get_weights())
        torch.save(learner.state_dict(), path)  # networks, targets, optimisers, counters
    """

    policy_kind: str  # "q" (ε-greedy on Q-values) or "softmax" (sample the policy)
    updates: int  # also the version of the weights get_weights() returns
    agent: AgentNet  # the acting network; in one process actors may act with it directly
    acting: ActingSpec  # how another process builds that network (rollout actors)

    def step(self, batch: EpisodeBatch, extra: EpisodeBatch | None = None) -> dict[str, float]: ...
    def sync_targets(self, episodes: int) -> bool: ...
    def get_weights(self) -> VersionedWeights: ...
    def state_dict(self) -> dict[str, Any]: ...
    def load_state_dict(self, state: dict[str, Any]) -> None: ...


@dataclass(frozen=True)
class AlgoSpec:
    """A registered algorithm.

    Attributes:
        name: the `--algo` name.
        config_cls: its frozen config dataclass (the `algo:` section of a run config).
        build: `(config, schema, n_ensemble, device) -> Learner`.
        description: one line for help texts.
        family: "value" or "pg"; decides the buffer tables (cluster.config.train.data_plan).
        extended: for "pg", whether the learner also takes an off-policy replay batch.
        reads_state: `(config) -> bool`, whether the learner reads the episodes' global
            state; when it does not, the buffer does not store it (`DataPlan.store_state`).
    """

    name: str
    config_cls: type
    build: Callable[[Any, EpisodeSchema, int, str], Learner]
    description: str
    family: str = "value"  # "value" (replay, ε-greedy) or "pg" (cycling buffer, sampling)
    extended: bool = False  # pg only: semi-online cycling buffer + off-policy critic pass
    reads_state: Callable[[Any], bool] = lambda cfg: True


def _cac(extended: bool, masked: bool) -> Callable[[Any, EpisodeSchema, int, str], Learner]:
    return lambda cfg, schema, e, device: CACLearner(cfg, schema, extended, masked, e, device)


def _value(mixing: str) -> Callable[[Any, EpisodeSchema, int, str], Learner]:
    return lambda cfg, schema, e, device: ValueLearner(cfg, schema, mixing, e, device)


def _pg_reads_state(cfg: CACConfig) -> bool:
    return cfg.critic_input != "obs"  # learner.pg.critic_features


NO_STATE: dict[str, Any] = {"reads_state": lambda cfg: False}  # the networks see observations
PG_STATE: dict[str, Any] = {"reads_state": _pg_reads_state}

ALGOS: dict[str, AlgoSpec] = {
    "iql": AlgoSpec("iql", ValueConfig, _value("none"), "independent Q-learning", **NO_STATE),
    "vdn": AlgoSpec("vdn", ValueConfig, _value("sum"), "value decomposition by sum", **NO_STATE),
    "qmix": AlgoSpec("qmix", ValueConfig, _value("qmix"), "QMIX, mixer conditioned on the state"),
    "qmix_ns": AlgoSpec(
        "qmix_ns",
        ValueConfig,
        _value("qmix_ns"),
        "QMIX, mixer conditioned on the joint observation",
        **NO_STATE,
    ),
    "rdn": AlgoSpec(
        "rdn",
        RDNConfig,
        lambda c, s, e, d: RDNLearner(c, s, e, d),
        "relevance decomposition network",
        **NO_STATE,
    ),
    "cac": AlgoSpec(
        "cac",
        CACConfig,
        _cac(extended=False, masked=False),
        "centralised actor-critic, fresh episodes only",
        family="pg",
        **PG_STATE,
    ),
    "ecac": AlgoSpec(
        "ecac",
        CACConfig,
        _cac(extended=True, masked=False),
        "CAC + semi-online cycling buffer and an off-policy critic pass",
        family="pg",
        extended=True,
        **PG_STATE,
    ),
    "mcac": AlgoSpec(
        "mcac",
        CACConfig,
        _cac(extended=False, masked=True),
        "CAC + KL mask against a Polyak-averaged policy",
        family="pg",
        **PG_STATE,
    ),
    "emcac": AlgoSpec(
        "emcac",
        CACConfig,
        _cac(extended=True, masked=True),
        "extended-masked CAC: cycling buffer, off-policy critic pass and KL mask",
        family="pg",
        extended=True,
        **PG_STATE,
    ),
    "coma": AlgoSpec(
        "coma",
        COMAConfig,
        lambda c, s, e, d: COMALearner(c, s, e, d),
        "COMA, counterfactual baseline",
        family="pg",
    ),
}


def get_algo(name: str) -> AlgoSpec:
    """Return the spec of `name`; unknown names raise ValueError listing the valid ones."""
    try:
        return ALGOS[name]
    except KeyError:
        raise ValueError(
            f"unknown algorithm {name!r}; valid algorithms: {', '.join(sorted(ALGOS))}"
        ) from None
