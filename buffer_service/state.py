"""In-memory state of the buffer: episodes, tables, and the idempotency record.

Every mutation goes through `insert` and `apply_sample`, which are deterministic given
their arguments, so replaying the log after a crash rebuilds exactly the same state.
"""

from __future__ import annotations

import logging
import random
from dataclasses import dataclass
from typing import Any

from buffer_service.config import BufferConfig
from buffer_service.episode import Episode, EpisodeSchema
from buffer_service.packed import PackedEpisode
from buffer_service.tables import Key, Table, TableCopy

log = logging.getLogger(__name__)


class SeqWindow:
    """episode_seq values seen from one actor: an exact set above a floor.

    Everything at or below ``floor`` counts as seen, so memory stays bounded by
    ``window`` per actor while a retry of a recent insert is still recognised exactly.
    """

    def __init__(self, window: int, floor: int = -(2**63), seen: list[int] | None = None):
        self.window = window
        self.floor = floor
        self.seen: set[int] = set(seen or ())

    def __contains__(self, seq: int) -> bool:
        return seq <= self.floor or seq in self.seen

    def add(self, seq: int) -> None:
        self.seen.add(seq)
        if len(self.seen) > self.window:
            ordered = sorted(self.seen)
            cut = len(ordered) // 2
            self.floor = ordered[cut - 1]
            self.seen = set(ordered[cut:])


@dataclass
class StateCopy:
    """`BufferState.capture`'s result: the state at one moment, for a snapshot."""

    schema: EpisodeSchema | None
    tables: dict[str, TableCopy]
    dedup: list[tuple[int, int, set[int]]]
    duplicates: int
    episodes: list[PackedEpisode]

    def header(self) -> dict[str, Any]:
        """The snapshot header: everything but the episodes (built off the event loop)."""
        return {
            "schema": self.schema.to_dict() if self.schema else None,
            "tables": {name: t.to_state() for name, t in self.tables.items()},
            "dedup": [[a, floor, sorted(seen)] for a, floor, seen in self.dedup],
            "duplicates": self.duplicates,
        }


class BufferState:
    """Episodes shared by the tables that hold them (stored once, packed, freed when
    unreferenced; without their state unless cfg.store_state).

    Args:
        cfg: server config (tables, dedup window, initial schema).
    """

    def __init__(self, cfg: BufferConfig) -> None:
        self.cfg = cfg
        self.schema: EpisodeSchema | None = cfg.schema
        self.tables: dict[str, Table] = {t.name: Table(t) for t in cfg.tables}
        self.episodes: dict[Key, PackedEpisode] = {}
        self.refs: dict[Key, int] = {}
        self.dedup: dict[int, SeqWindow] = {}
        self.duplicates = 0

    def is_duplicate(self, key: Key) -> bool:
        w = self.dedup.get(key[0])
        return w is not None and key[1] in w

    def insert(self, ep: Episode | PackedEpisode, table_names: list[str]) -> bool:
        """Store `ep` (packed) in `table_names` unless its key was seen; return True if
        stored."""
        key = ep.key
        if self.is_duplicate(key):
            self.duplicates += 1
            return False
        self.dedup.setdefault(key[0], SeqWindow(self.cfg.dedup_window)).add(key[1])
        # Distinct configured names: a table listed twice (logs of older versions) holds the
        # episode once, and one dropped from the config since is skipped.
        names = [n for n in dict.fromkeys(table_names) if n in self.tables]
        if not names:
            return True
        ep = PackedEpisode.pack(ep, state=self.cfg.store_state)
        self.episodes[key] = ep
        self.refs[key] = len(names)
        for n in names:
            for old in self.tables[n].insert(key, ep.nbytes):
                self._unref(old)
        return True

    def _unref(self, key: Key) -> None:
        self.refs[key] -= 1
        if self.refs[key] == 0:
            del self.refs[key]
            del self.episodes[key]

    def choose(self, table: str, n: int, rng: random.Random) -> list[Key]:
        return self.tables[table].choose(n, rng)

    def apply_sample(self, table: str, keys: list[Key]) -> list[PackedEpisode]:
        """Count a sample of `keys` from `table`; return their episodes (before retiring)."""
        eps = [self.episodes[k] for k in keys if k in self.episodes]
        for old in self.tables[table].mark_sampled(keys):
            self._unref(old)
        return eps

    def stats(self) -> dict[str, Any]:
        return {
            "schema": self.schema.to_dict() if self.schema else None,
            "episodes_stored": len(self.episodes),
            "episode_bytes": sum(ep.nbytes for ep in self.episodes.values()),
            "duplicates": self.duplicates,
            "actors": len(self.dedup),
            "tables": {name: t.stats() for name, t in self.tables.items()},
        }

    def capture(self) -> StateCopy:
        """A copy of the references that make up the state, cheap enough to take on the event
        loop (flat C-level copies of the containers; the episodes are immutable and shared),
        from which another thread can serialise a snapshot while the state moves on."""
        return StateCopy(
            schema=self.schema,
            tables={name: t.capture() for name, t in self.tables.items()},
            dedup=[(a, w.floor, w.seen.copy()) for a, w in self.dedup.items()],
            duplicates=self.duplicates,
            episodes=list(self.episodes.values()),
        )

    def load_header(self, st: dict[str, Any]) -> None:
        if st["schema"] is not None:
            self.schema = EpisodeSchema.from_dict(st["schema"])
        for name, tst in st["tables"].items():
            if name in self.tables:
                self.tables[name].load_state(tst)
            else:
                log.warning("snapshot table %r is not configured any more; dropped", name)
        self.dedup = {a: SeqWindow(self.cfg.dedup_window, f, s) for a, f, s in st["dedup"]}
        self.duplicates = st["duplicates"]

    def rebuild_refs(self) -> None:
        """After loading a snapshot: drop the state if it is not stored, apply the tables'
        byte budgets, count references and drop unreferenced episodes."""
        for t in self.tables.values():  # a table may reference an episode the file lacks
            missing = [k for k in t.order if k not in self.episodes]
            for k in missing:
                log.error("snapshot lacks episode %s of table %s; dropped", k, t.name)
                t.order.remove(k)
                del t.times_sampled[k]
        if not self.cfg.store_state:
            self.episodes = {k: PackedEpisode.pack(ep, False) for k, ep in self.episodes.items()}
        sizes = {k: ep.nbytes for k, ep in self.episodes.items()}
        self.refs = {}
        for t in self.tables.values():
            t.set_sizes(sizes)
            for k in t.order:
                self.refs[k] = self.refs.get(k, 0) + 1
        for k in [k for k in self.episodes if k not in self.refs]:
            del self.episodes[k]
