"""Where a training run's time goes: nested wall-clock sections, off unless switched on.

The real loop, the rollout worker and the learner mark their parts with `timed(name)`;
`credit bench train` switches the accumulators on and reads them. Sections nest: a section
opened inside another is recorded under the path of both ("update/backward"), so the env
steps of an evaluation ("eval/env") are kept apart from those of training ("act/env").
Switched off (the default), a section costs one attribute test. One thread records at a time
(the loop's); the totals are not locked.

Calling loop::

    TIMERS.reset(enabled=True)
    with timed("update"):
        with timed("backward"):
            loss.backward()
    TIMERS.totals   # {"update/backward": 0.12, "update": 0.30}
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager


class Timers:
    """Seconds and counts per section path; see the module docstring."""

    def __init__(self) -> None:
        self.reset(enabled=False)

    def reset(self, enabled: bool) -> None:
        """Forget every total and switch recording on or off."""
        self.enabled = enabled
        self.totals: dict[str, float] = defaultdict(float)
        self.counts: dict[str, int] = defaultdict(int)
        self._stack: list[str] = []

    @contextmanager
    def section(self, name: str) -> Iterator[None]:
        """Add the wall time of the `with` body to `name` under the open sections."""
        if not self.enabled:
            yield
            return
        self._stack.append(name)
        key = "/".join(self._stack)
        started = time.perf_counter()
        try:
            yield
        finally:
            self.totals[key] += time.perf_counter() - started
            self.counts[key] += 1
            self._stack.pop()

    def iterate(self, name: str, items: Iterator) -> Iterator:
        """Yield from `items`, timing each `next` under `name` (not the consumer's work)."""
        it = iter(items)
        while True:
            with self.section(name):
                item = next(it, StopIteration)
            if item is StopIteration:
                return
            yield item

    def exclusive(self) -> dict[str, float]:
        """Each section's seconds less those of the sections directly inside it."""
        own = dict(self.totals)
        for key, seconds in self.totals.items():
            parent, _, _ = key.rpartition("/")
            if parent in own:
                own[parent] -= seconds
        return own


TIMERS = Timers()
timed = TIMERS.section
