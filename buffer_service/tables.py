"""Tables (cycling, replay) and their sample-to-insert rate limiter.

Pure bookkeeping over episode keys ``(actor_id, episode_seq)``; no I/O, no asyncio. The
server decides *when* to call these (waiting on the limiter); `BufferState` owns the
episodes the keys point at.
"""

from __future__ import annotations

import random
from collections import deque
from dataclasses import dataclass
from typing import Any

from buffer_service.config import RateLimiterConfig, TableConfig

Key = tuple[int, int]


class RateLimiter:
    """Reverb's SampleToInsertRatio (see `RateLimiterConfig` for the exact rule)."""

    def __init__(self, cfg: RateLimiterConfig) -> None:
        self.cfg = cfg
        self.inserts = 0
        self.samples = 0

    def _bounds(self) -> tuple[float, float, float]:
        spi = self.cfg.samples_per_insert
        offset = spi * self.cfg.min_size_to_sample
        diff = self.inserts * spi - self.samples
        return diff, offset - self.cfg.error_buffer, offset + self.cfg.error_buffer

    def can_sample(self, n: int, size: int) -> bool:
        """May `n` episodes be sampled from a table currently holding `size`?"""
        if size < self.cfg.min_size_to_sample:
            return False
        if self.cfg.samples_per_insert == 0:
            return True
        diff, lo, _ = self._bounds()
        return diff - n >= lo

    def can_insert(self, n: int = 1) -> bool:
        """May `n` more episodes be inserted?"""
        if self.cfg.samples_per_insert == 0:
            return True
        if self.inserts + n <= self.cfg.min_size_to_sample:
            return True
        diff, _, hi = self._bounds()
        return diff + n * self.cfg.samples_per_insert <= hi


@dataclass
class TableCopy:
    """A table's keys, sample counts and counters at one moment (`Table.capture`)."""

    order: list[Key]
    times_sampled: dict[Key, int]
    counters: tuple[int, int, int, int]  # inserts, samples, evicted, retired

    def to_state(self) -> dict[str, Any]:
        inserts, samples, evicted, retired = self.counters
        return {
            "items": [[k[0], k[1], self.times_sampled[k]] for k in self.order],
            "inserts": inserts,
            "samples": samples,
            "evicted": evicted,
            "retired": retired,
        }


class Table:
    """FIFO-ordered episode keys with per-key sample counts and stored sizes.

    Two bounds hold after every insert, both by dropping the oldest keys (FIFO, for both
    kinds): at most ``capacity`` episodes, and at most ``max_bytes`` bytes of them (when
    set; the newest episode is kept even if it alone is larger).

    Args:
        cfg: the table's config (kind, capacity, max_bytes, K, rate limiter).
    """

    def __init__(self, cfg: TableConfig) -> None:
        self.cfg = cfg
        self.name = cfg.name
        self.order: deque[Key] = deque()
        self.times_sampled: dict[Key, int] = {}
        self.sizes: dict[Key, int] = {}  # stored bytes of each key's episode
        self.bytes = 0  # their sum
        self.limiter = RateLimiter(cfg.rate_limiter)
        self.evicted = 0  # dropped on overflow
        self.retired = 0  # removed after K samples

    def __len__(self) -> int:
        return len(self.order)

    def __contains__(self, key: Key) -> bool:
        return key in self.times_sampled

    def insert(self, key: Key, nbytes: int = 0) -> list[Key]:
        """Append `key` (its episode stored in `nbytes`); return the keys dropped from the
        front to respect capacity and max_bytes."""
        self.order.append(key)
        self.times_sampled[key] = 0
        self.sizes[key] = nbytes
        self.bytes += nbytes
        self.limiter.inserts += 1
        dropped = self._fit()
        self.evicted += len(dropped)
        return dropped

    def _over(self) -> bool:
        budget = self.cfg.max_bytes
        return len(self.order) > self.cfg.capacity or (
            budget > 0 and self.bytes > budget and len(self.order) > 1
        )

    def _fit(self) -> list[Key]:
        """Drop the oldest keys until both bounds hold; return them."""
        dropped = []
        while self._over():
            old = self.order.popleft()
            del self.times_sampled[old]
            self.bytes -= self.sizes.pop(old)
            dropped.append(old)
        return dropped

    def set_sizes(self, sizes: dict[Key, int]) -> list[Key]:
        """After loading a snapshot: every key's stored bytes; drops (and returns) the oldest
        keys beyond max_bytes (the budget may have shrunk between runs)."""
        self.sizes = {k: sizes[k] for k in self.order}
        self.bytes = sum(self.sizes.values())
        dropped = self._fit()
        self.evicted += len(dropped)
        return dropped

    def ready(self, n: int) -> bool:
        """Can a batch of `n` be sampled now (limiter and, for cycling, enough episodes)?"""
        size = len(self.order)
        if size == 0 or (self.distinct and size < n):
            return False
        return self.limiter.can_sample(n, size)

    @property
    def distinct(self) -> bool:
        """Does a batch hold distinct episodes (cycling, or replay without replacement)?"""
        return self.cfg.kind == "cycling" or not self.cfg.replacement

    def choose(self, n: int, rng: random.Random) -> list[Key]:
        """Pick `n` keys uniformly: without replacement for cycling tables and replay tables
        with `replacement` off, with replacement otherwise."""
        size = len(self.order)
        if self.distinct:
            idx = rng.sample(range(size), n)
        else:
            idx = [rng.randrange(size) for _ in range(n)]
        return [self.order[i] for i in idx]

    def mark_sampled(self, keys: list[Key]) -> list[Key]:
        """Count one sample per key; return keys retired for reaching K (cycling only)."""
        self.limiter.samples += len(keys)
        k = self.cfg.max_times_sampled if self.cfg.kind == "cycling" else 0
        retired = []
        for key in keys:
            if key not in self.times_sampled:  # replayed log naming an evicted key
                continue
            self.times_sampled[key] += 1
            if k and self.times_sampled[key] >= k:
                retired.append(key)
        for key in retired:
            del self.times_sampled[key]
            self.bytes -= self.sizes.pop(key, 0)
            self.order.remove(key)
        self.retired += len(retired)
        return retired

    def stats(self) -> dict[str, Any]:
        return {
            "kind": self.cfg.kind,
            "size": len(self.order),
            "capacity": self.cfg.capacity,
            "bytes": self.bytes,
            "max_bytes": self.cfg.max_bytes,
            "inserts": self.limiter.inserts,
            "samples": self.limiter.samples,
            "evicted": self.evicted,
            "retired": self.retired,
        }

    def to_state(self) -> dict[str, Any]:
        """Snapshot form: keys in FIFO order with their counts, plus limiter totals."""
        return self.capture().to_state()

    def capture(self) -> TableCopy:
        """The table at this moment, copied cheaply (see `BufferState.capture`)."""
        counters = (self.limiter.inserts, self.limiter.samples, self.evicted, self.retired)
        return TableCopy(list(self.order), dict(self.times_sampled), counters)

    def load_state(self, st: dict[str, Any]) -> None:
        self.order.clear()
        self.times_sampled.clear()
        self.sizes, self.bytes = {}, 0  # known once the episodes are (`set_sizes`)
        for actor, seq, count in st["items"]:
            if (actor, seq) in self.times_sampled:  # listed twice by an older version
                continue
            self.order.append((actor, seq))
            self.times_sampled[(actor, seq)] = count
        while len(self.order) > self.cfg.capacity:  # capacity shrank between runs
            del self.times_sampled[self.order.popleft()]
        self.sizes = dict.fromkeys(self.order, 0)
        self.limiter.inserts = st["inserts"]
        self.limiter.samples = st["samples"]
        self.evicted = st["evicted"]
        self.retired = st["retired"]
