"""The buffer service's tables in one process, for `--mode local`.

Same `BufferState` and `Table` classes as the TCP server, so a local run and a cluster run
sample with the same semantics (rate limiter included) and validate episodes alike; only the
transport and the durability differ. `write`/`read` store the tables in the service's
snapshot format (`buffer_service.storage`), so a checkpoint can keep them.
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

from buffer_service.config import BufferConfig, TableConfig
from buffer_service.episode import Episode, EpisodeBatch, EpisodeSchema
from buffer_service.packed import PackedEpisode
from buffer_service.state import BufferState
from buffer_service.storage import Storage


class LocalBuffer:
    """In-process tables with the client's calling pattern.

    Calling loop::

        buf = LocalBuffer((TableConfig(name="replay", kind="replay", capacity=1000),), seed=0)
        if buf.can_insert():                    # the rate limiter of every table
            buf.insert(episodes)                # into every table
        if buf.ready("replay", 32):
            batch = buf.sample("replay", 32)    # EpisodeBatch [32, ...]
        buf.write(folder)                       # a snapshot folder; LocalBuffer.read(folder)

    Args:
        tables: the tables to hold.
        seed: seed of the sampling RNG.
        schema: when given, every inserted episode is validated against it (EpisodeError),
            as the buffer service does.
        store_state: keep the episodes' state (False for learners that never read it).

    Episodes are stored packed (`buffer_service.packed`); `sample` decodes them into the
    batch's arrays.
    """

    def __init__(
        self,
        tables: tuple[TableConfig, ...],
        seed: int = 0,
        schema: EpisodeSchema | None = None,
        store_state: bool = True,
    ):
        self.tables = tables
        cfg = BufferConfig(tables=tables, schema=schema, store_state=store_state)
        self.state = BufferState(cfg)
        self.rng = random.Random(seed)

    def can_insert(self) -> bool:
        """Would the buffer service accept an insert now (every table's limiter)?"""
        return all(t.limiter.can_insert(1) for t in self.state.tables.values())

    def insert(
        self, episodes: list[Episode | PackedEpisode], tables: list[str] | None = None
    ) -> dict[str, int]:
        """Store `episodes` (validated first, all or nothing) in `tables` (default: all).
        Without store_state an episode may come without its state ([T+1, 0])."""
        if self.state.schema is not None:
            for ep in episodes:
                if isinstance(ep, PackedEpisode):
                    ep.validate(self.state.schema)
                else:
                    empty = not self.state.cfg.store_state and ep.state.shape[-1:] == (0,)
                    ep.validate(self.state.schema, state=not empty)
        names = list(self.state.tables) if tables is None else tables
        stored = sum(self.state.insert(ep, names) for ep in episodes)
        return {"inserted": stored, "duplicates": len(episodes) - stored}

    def ready(self, table: str, batch_size: int) -> bool:
        return self.state.tables[table].ready(batch_size)

    def sample_episodes(self, table: str, batch_size: int) -> list[PackedEpisode]:
        """`batch_size` episodes of `table` (the caller checked `ready`)."""
        keys = self.state.choose(table, batch_size, self.rng)
        return self.state.apply_sample(table, keys)

    def sample(self, table: str, batch_size: int) -> EpisodeBatch:
        return EpisodeBatch.from_episodes(self.sample_episodes(table, batch_size))

    def stats(self) -> dict[str, Any]:
        return self.state.stats()

    def rng_state(self) -> Any:
        return self.rng.getstate()

    def set_rng_state(self, state: Any) -> None:
        self.rng.setstate(state)

    def write(self, folder: Path) -> None:
        """Write the tables (episodes, sample counts, limiter totals, dedup record) to a new
        `folder` as a buffer-service snapshot folder (fsynced)."""
        storage = Storage(str(folder), fsync=True, tables=self.tables)
        storage.restore(BufferState(self.state.cfg))  # a new folder: opens its first log
        storage.snapshot(self.state)
        storage.close()

    def read(self, folder: Path) -> None:
        """Replace the tables' contents with those `write` (or a buffer service) left in
        `folder`; raises StorageError when the folder cannot be restored completely."""
        state = BufferState(self.state.cfg)
        Storage(str(folder), tables=self.tables, read_only=True).restore(state)
        self.state = state
