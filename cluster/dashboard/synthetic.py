"""A synthetic metrics feed: real exporters from `cluster.metrics`, fed made-up numbers.

For previewing the dashboard without a training run, and for the dashboard/Prometheus tests
until they drive a real one. Everything goes through the public API of `cluster.metrics`
(per episode batch / per update, like the trainer), and the endpoints are listed in a
file-SD file exactly as the launcher does:

    python -m cluster.dashboard.synthetic --sd-file /tmp/t.json --actors 2
    credit dashboard --sd-file /tmp/t.json

The buffer's metrics are not invented here; they appear only where `buffer_service.metrics`
exists and offers `BufferMetrics`.
"""

from __future__ import annotations

import argparse
import logging
import math
import random
import signal
import threading

from cluster.metrics import ActorMetrics, LearnerMetrics, serve, stop, write_file_sd

log = logging.getLogger(__name__)


class SyntheticFeed:
    """`n_actors` actor exporters and one learner exporter updated from a thread.

    Args:
        n_actors: how many actor exporters.
        period_s: seconds between updates.
        seed: random seed of the made-up numbers.
    """

    def __init__(self, n_actors: int = 2, period_s: float = 0.2, seed: int = 0) -> None:
        if n_actors < 1 or period_s <= 0:
            raise ValueError("need n_actors >= 1 and period_s > 0")
        self.actors = [ActorMetrics(i) for i in range(n_actors)]
        self.learner = LearnerMetrics()
        self.period_s = period_s
        self._rng = random.Random(seed)
        self.endpoints = [serve(a.registry) for a in self.actors] + [serve(self.learner.registry)]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="synthetic-feed", daemon=True)

    def step(self, k: int) -> None:
        """One round of updates (k counts rounds); what a trainer does per batch."""
        rng = self._rng
        version = k // 2
        for i, actor in enumerate(self.actors):
            episodes = rng.randint(1, 3)
            actor.record(episodes, episodes * rng.randint(20 + 5 * i, 60))
            actor.set_weights_version(max(0, version - rng.randint(0, 2)))
        if k % 2 == 0:
            loss = 2.0 * math.exp(-k / 300) + 0.05 * rng.random()
            self.learner.record_update(
                0.02 + 0.01 * rng.random(),
                {"critic": loss, "actor": -0.3 * loss},
                weights_version=version,
            )
            self.learner.record_policy_lag(rng.choice((0, 1, 1, 2, 3)) for _ in range(4))
            self.learner.set_kl_masked_fraction(0.1 + 0.05 * math.sin(k / 20))
        if k % 25 == 0:
            progress = 1 - math.exp(-k / 400)
            self.learner.record_test(20 * progress, win_rate=min(1.0, progress))
        if k % 150 == 149:
            self.learner.actor_restarted()

    def _run(self) -> None:
        k = 0
        while not self._stop.wait(self.period_s):
            self.step(k)
            k += 1

    def start(self) -> SyntheticFeed:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        for ep in self.endpoints:
            stop(ep)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sd-file", required=True, help="file_sd JSON to write the endpoints to")
    p.add_argument("--actors", type=int, default=2, help="number of actor exporters")
    p.add_argument("--duration", type=float, default=0, help="seconds to run (0 = until killed)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    feed = SyntheticFeed(args.actors).start()
    write_file_sd(args.sd_file, feed.endpoints, {"source": "synthetic"})
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    try:
        done.wait(args.duration or None)
    except KeyboardInterrupt:
        pass
    finally:
        feed.close()
    log.info("synthetic feed stopped")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
