"""What a run shows as it goes: the learner metrics' means between evaluations
(`MetricMeans`) and the progress line (`Progress`)."""

from __future__ import annotations

import copy
import logging
import sys
import time

log = logging.getLogger(__name__)


class MetricMeans:
    """The latest update's learner metrics, and each metric's running mean since `take`."""

    def __init__(self) -> None:
        self.last: dict[str, float] = {}
        self.sums: dict[str, list[float]] = {}  # key -> [sum, count] since `take`

    def record(self, metrics: dict[str, float]) -> None:
        self.last = metrics
        for k, v in metrics.items():
            acc = self.sums.setdefault(k, [0.0, 0])
            acc[0] += float(v)
            acc[1] += 1

    def take(self) -> dict[str, float]:
        """Each metric's mean over the updates since the previous call."""
        means = {k: total / n for k, (total, n) in self.sums.items()}
        self.sums = {}
        return means

    def state(self) -> dict[str, list[float]]:
        """The sums not yet taken, for a checkpoint."""
        return copy.deepcopy(self.sums)

    def load_state(self, sums: dict[str, list[float]]) -> None:
        self.sums = sums


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
