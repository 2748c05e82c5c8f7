"""Prometheus metrics of the actors and the learner (docs/design.md, "Metrics"), defined once, here.

Every component owns its own `CollectorRegistry`, so several exporters (one per actor, one for
the learner) can live in one process, as they do in `--mode local` and in tests. Everything is
recorded per episode batch or per update, never per environment step, and no label carries a
per-step value. The buffer's `credit_buffer_*` metrics live in `buffer_service/metrics.py`.

The calling loop::

    actor = ActorMetrics(actor_id=3)
    host, port = serve(actor.registry)              # 127.0.0.1, a free port
    while running:
        episodes = worker.collect(4)
        actor.record(len(episodes), sum(int(e.filled.sum()) for e in episodes))

    learner = LearnerMetrics()
    serve(learner.registry, port=0)
    learner.record_update(seconds, {"critic": 0.3, "actor": -0.1}, weights_version=12)
    learner.record_policy_lag([12 - e.policy_version for e in batch_episodes])

The launcher lists every endpoint in a Prometheus file-service-discovery file with
`write_file_sd`; `credit metrics up` and `credit dashboard` read it.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
)

log = logging.getLogger(__name__)

#: Loopback only unless a caller asks otherwise (docs/design.md: bind 127.0.0.1 by default).

#: Seconds per learner update: from a millisecond (tiny nets) to a minute (huge batches).
# fmt: off
UPDATE_SECONDS_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5,
                          1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
# fmt: on
#: Versions between the policy that acted and the learner's current one: 0, then 1, 2, 3, 4,
#: 6, 8, 12, ... (each power of two and 1.5 times it) up to 2^20. Replayed episodes are
#: thousands of versions old on long runs (a top bucket of 128 clamped every percentile
#: there); past the top, PromQL's histogram_quantile answers the top bucket's bound.
POLICY_LAG_BUCKETS = tuple(
    sorted({0, 1, *(2**k for k in range(1, 21)), *(3 * 2**k for k in range(19))})
)

#: Every name a scrape of an actor or learner exporter can show (counters with `_total`).
ACTOR_METRIC_NAMES = (
    "credit_env_steps_total",
    "credit_episodes_total",
    "credit_weights_version",
)
LEARNER_METRIC_NAMES = (
    "credit_learner_updates_total",
    "credit_learner_update_seconds",
    "credit_policy_lag_versions",
    "credit_weights_version",
    "credit_loss",
    "credit_test_return",
    "credit_test_win_rate",
    "credit_kl_masked_fraction",
    "credit_actor_restarts_total",
)
#: The learner's credit_run_info{algo, family} = 1 when the launcher names the algorithm: what
#: the dashboard picks its panels by (no chart of its own).
RUN_INFO_NAME = "credit_run_info"


def _counter_name(name: str) -> str:
    # prometheus-client appends `_total` itself; give it the stem so the exposed name is exact.
    return name.removesuffix("_total")


class ActorMetrics:
    """The metrics of one rollout actor, in a registry of its own.

    Args:
        actor_id: the actor's id; becomes the `actor` label (one value per actor, bounded).
        registry: registry to register in; a fresh one when None.
    """

    def __init__(self, actor_id: int | str, registry: CollectorRegistry | None = None) -> None:
        self.actor_id = str(actor_id)
        self.registry = registry if registry is not None else CollectorRegistry()
        self._env_steps = Counter(
            _counter_name("credit_env_steps_total"),
            "Environment steps taken by this actor (summed per episode).",
            ["actor"],
            registry=self.registry,
        ).labels(actor=self.actor_id)
        self._episodes = Counter(
            _counter_name("credit_episodes_total"),
            "Episodes completed by this actor.",
            ["actor"],
            registry=self.registry,
        ).labels(actor=self.actor_id)
        self._version = Gauge(
            "credit_weights_version",
            "Version of the policy weights this component holds.",
            ["component"],
            registry=self.registry,
        ).labels(component=f"actor-{self.actor_id}")

    def record(self, episodes: int, env_steps: int) -> None:
        """Count a batch of finished episodes.

        Args:
            episodes: how many episodes finished (>= 0).
            env_steps: their environment steps, padding excluded (>= 0).
        """
        if episodes < 0 or env_steps < 0:
            raise ValueError(f"episodes and env_steps must be >= 0, got {episodes}, {env_steps}")
        self._episodes.inc(episodes)
        self._env_steps.inc(env_steps)

    def set_weights_version(self, version: int) -> None:
        """Record the weights version the actor now acts with."""
        self._version.set(version)


class LearnerMetrics:
    """The learner's metrics (and the launcher's actor-restart count), in one registry.

    Args:
        registry: registry to register in; a fresh one when None.
        algo, family: the run's algorithm and its family ("value" or "pg"), exposed as
            credit_run_info{algo, family} = 1 so that a dashboard shows the panels that
            algorithm feeds (not exposed without algo).
    """

    def __init__(
        self,
        registry: CollectorRegistry | None = None,
        algo: str | None = None,
        family: str | None = None,
    ) -> None:
        r = self.registry = registry if registry is not None else CollectorRegistry()
        if algo is not None:
            info = Gauge(
                RUN_INFO_NAME, "The run's algorithm (value 1).", ["algo", "family"], registry=r
            )
            info.labels(algo=algo, family=family or "").set(1)
        self._updates = Counter(
            _counter_name("credit_learner_updates_total"), "Learner updates done.", registry=r
        )
        self._update_seconds = Histogram(
            "credit_learner_update_seconds",
            "Wall time of one learner update, in seconds.",
            buckets=UPDATE_SECONDS_BUCKETS,
            registry=r,
        )
        self._lag = Histogram(
            "credit_policy_lag_versions",
            "Learner version minus the version that acted, per trained episode.",
            buckets=POLICY_LAG_BUCKETS,
            registry=r,
        )
        self._version = Gauge(
            "credit_weights_version",
            "Version of the policy weights this component holds.",
            ["component"],
            registry=r,
        ).labels(component="learner")
        self._loss = Gauge("credit_loss", "Last value of each loss term.", ["name"], registry=r)
        self._test_return = Gauge(
            "credit_test_return", "Mean return of the last greedy test episodes.", registry=r
        )
        self._win_rate = Gauge(
            "credit_test_win_rate", "Win rate (0-1) of the last greedy test episodes.", registry=r
        )
        self._kl_masked = Gauge(
            "credit_kl_masked_fraction",
            "Fraction (0-1) of timesteps whose advantage the EM-CAC KL mask zeroed.",
            registry=r,
        )
        self._restarts = Counter(
            _counter_name("credit_actor_restarts_total"),
            "Rollout actors restarted after a failure.",
            registry=r,
        )

    def record_update(
        self, seconds: float, losses: Mapping[str, float], weights_version: int
    ) -> None:
        """Record one learner update.

        Args:
            seconds: wall time of the update.
            losses: loss term name -> value (a handful of fixed names, e.g. "critic", "actor").
            weights_version: version of the weights after the update.
        """
        if seconds < 0:
            raise ValueError(f"update seconds must be >= 0, got {seconds}")
        self._updates.inc()
        self._update_seconds.observe(seconds)
        for name, value in losses.items():
            self._loss.labels(name=name).set(float(value))
        self._version.set(weights_version)

    def record_policy_lag(self, lags: Iterable[int]) -> None:
        """Record the policy lag (in versions) of each episode of a trained batch."""
        for lag in lags:
            self._lag.observe(max(0, int(lag)))

    def record_test(self, return_mean: float, win_rate: float | None = None) -> None:
        """Record a test (greedy evaluation) result.

        Args:
            return_mean: mean episode return.
            win_rate: fraction of won episodes in [0, 1]; None where the env has no winner.
        """
        self._test_return.set(float(return_mean))
        if win_rate is not None:
            if not 0.0 <= win_rate <= 1.0:
                raise ValueError(f"win_rate must be in [0, 1], got {win_rate}")
            self._win_rate.set(float(win_rate))

    def set_kl_masked_fraction(self, fraction: float) -> None:
        """Record the fraction of timesteps the KL mask zeroed in the last update (EM-CAC)."""
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"KL-masked fraction must be in [0, 1], got {fraction}")
        self._kl_masked.set(float(fraction))

    def actor_restarted(self, count: int = 1) -> None:
        """Count rollout-actor restarts (called by whoever restarts them)."""
        self._restarts.inc(count)


def exposed_names(registry: CollectorRegistry) -> set[str]:
    """The metric names a scrape of `registry` shows (histograms by their base name).

    Returns:
        e.g. {"credit_env_steps_total", "credit_learner_update_seconds", ...}
    """
    names: set[str] = set()
    for family in registry.collect():
        names.add(f"{family.name}_total" if family.type == "counter" else family.name)
    return names
