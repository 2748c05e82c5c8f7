"""Cumulative counters of the learner loop (`cluster.loop.TrainLoop`, both modes; no Ray
here, so tests and benchmarks can use them without connecting anywhere)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field


@dataclass
class LoopStats:
    """Cumulative counters of the learner loop, cheap enough to keep always (read by
    `credit bench scaling` between windows; never reset).

    Attributes:
        updates: learner steps taken by this loop.
        update_s: seconds inside those steps (`learner.step`).
        publish_s: seconds publishing weights (ray.put and the coordinator round trip).
        consumed_env_steps: transitions (filled steps) in the batches those steps trained on.
        sample_requests: sample requests sent to the buffer service.
        sample_s: seconds spent inside those requests (rate-limiter wait, transfer, decode).
        sample_timeouts: requests the rate limiter refused within cluster.sample_timeout_s.
        dropped_stale: sampled episodes dropped for exceeding run.max_policy_lag.
        lag_counts: policy lag at sample time (learner version minus the episode's
            policy_version, clipped at 0) -> how many sampled episodes had it.
    """

    updates: int = 0
    update_s: float = 0.0
    publish_s: float = 0.0
    consumed_env_steps: int = 0
    sample_requests: int = 0
    sample_s: float = 0.0
    sample_timeouts: int = 0
    dropped_stale: int = 0
    lag_counts: Counter = field(default_factory=Counter)

    def snapshot(self) -> dict:
        """A copy safe to keep while the loop goes on (lag_counts copied)."""
        return {
            "updates": self.updates,
            "update_s": self.update_s,
            "publish_s": self.publish_s,
            "consumed_env_steps": self.consumed_env_steps,
            "sample_requests": self.sample_requests,
            "sample_s": self.sample_s,
            "sample_timeouts": self.sample_timeouts,
            "dropped_stale": self.dropped_stale,
            "lag_counts": dict(self.lag_counts),
        }
