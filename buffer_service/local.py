"""The buffer service's tables in one process, for `--mode local`.

Same `BufferState` and `Table` classes as the TCP server, so a local run and a cluster run
sample with the same semantics; only the transport (and durability) differ.
"""

from __future__ import annotations

import random
from typing import Any

from buffer_service.config import BufferConfig, TableConfig
from buffer_service.episode import Episode, EpisodeBatch
from buffer_service.state import BufferState


class LocalBuffer:
    """In-process tables with the client's calling pattern.

    Calling loop::

        buf = LocalBuffer((TableConfig(name="replay", kind="replay", capacity=1000),), seed=0)
        buf.insert(episodes)                    # into every table
        if buf.ready("replay", 32):
            batch = buf.sample("replay", 32)    # EpisodeBatch [32, ...]
    """

    def __init__(self, tables: tuple[TableConfig, ...], seed: int = 0):
        self.state = BufferState(BufferConfig(tables=tables))
        self.rng = random.Random(seed)

    def insert(self, episodes: list[Episode], tables: list[str] | None = None) -> dict[str, int]:
        names = list(self.state.tables) if tables is None else tables
        stored = sum(self.state.insert(ep, names) for ep in episodes)
        return {"inserted": stored, "duplicates": len(episodes) - stored}

    def ready(self, table: str, batch_size: int) -> bool:
        return self.state.tables[table].ready(batch_size)

    def sample(self, table: str, batch_size: int) -> EpisodeBatch:
        keys = self.state.choose(table, batch_size, self.rng)
        return EpisodeBatch.from_episodes(self.state.apply_sample(table, keys))

    def stats(self) -> dict[str, Any]:
        return self.state.stats()

    def rng_state(self) -> Any:
        return self.rng.getstate()

    def set_rng_state(self, state: Any) -> None:
        self.rng.setstate(state)
