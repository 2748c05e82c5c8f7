"""Frozen configs of the buffer service: one per table and one for the server."""

from __future__ import annotations

import ipaddress
import math
from dataclasses import dataclass, field, fields
from typing import Any

from buffer_service.episode import EpisodeSchema

TABLE_KINDS = ("cycling", "replay")
# A replay's default byte budget (per seed): 5,000 bane_vs_bane episodes as long as its
# episode limit (200 steps) at the 3.6 KB per stored env step `credit bench memory` measured
# with the state (3.3 KB without) need 3.4 GiB; at the measured mean length (54 steps) 0.9.
DEFAULT_REPLAY_MAX_BYTES = 4 * 2**30


@dataclass(frozen=True)
class RateLimiterConfig:
    """Reverb-style SampleToInsertRatio limiter of one table.

    With ``diff = inserts * samples_per_insert - samples`` (totals since the table was
    created; one sampled episode counts one sample), ``offset = samples_per_insert *
    min_size_to_sample``, a sample of n episodes may proceed when the table holds at least
    ``min_size_to_sample`` episodes and ``diff - n >= offset - error_buffer``; an insert may
    proceed while fewer than ``min_size_to_sample`` episodes were ever inserted or
    ``diff + samples_per_insert <= offset + error_buffer``. ``samples_per_insert = 0`` turns
    the ratio off (a plain MinSize limiter).

    Attributes:
        min_size_to_sample: episodes the table must hold before any sample.
        samples_per_insert: target sampled episodes per inserted episode (0 = no ratio).
        error_buffer: slack around the target, in samples (must be >= samples_per_insert
            when the ratio is on, or nothing could ever proceed).
    """

    min_size_to_sample: int = 1
    samples_per_insert: float = 0.0
    error_buffer: float = math.inf

    def validate(self) -> None:
        if self.min_size_to_sample < 1:
            raise ValueError("rate_limiter.min_size_to_sample must be >= 1")
        if self.samples_per_insert < 0:
            raise ValueError("rate_limiter.samples_per_insert must be >= 0")
        if self.samples_per_insert > 0 and self.error_buffer < self.samples_per_insert:
            raise ValueError("rate_limiter.error_buffer must be >= samples_per_insert")


@dataclass(frozen=True)
class TableConfig:
    """One table of the buffer.

    Attributes:
        name: table name clients sample from.
        kind: ``cycling`` (FIFO; each episode sampled at most ``max_times_sampled`` times,
            then removed; a batch never repeats an episode) or ``replay`` (uniform).
        capacity: episodes held; the oldest is dropped on overflow (both kinds).
        max_bytes: byte budget of the episodes held (their stored, packed size,
            `buffer_service.packed.PackedEpisode.nbytes`); the oldest are dropped beyond it
            (both kinds; 0 = no budget, the count alone bounds the table).
        max_times_sampled: K for ``cycling`` (0 = unlimited); ignored for ``replay``.
        replacement: ``replay`` only: a batch may repeat an episode (True) or never does
            (False; a batch then needs at least as many episodes held as it asks for).
        rate_limiter: sample/insert back-pressure of this table.
    """

    name: str = "cycling"
    kind: str = "cycling"
    capacity: int = 32
    max_bytes: int = 0
    max_times_sampled: int = 8
    replacement: bool = True
    rate_limiter: RateLimiterConfig = field(default_factory=RateLimiterConfig)

    def validate(self) -> None:
        if not self.name or not self.name.isidentifier():
            raise ValueError(f"table.name {self.name!r} must be a non-empty identifier")
        if self.kind not in TABLE_KINDS:
            raise ValueError(f"table.kind {self.kind!r} must be one of {TABLE_KINDS}")
        if self.capacity < 1:
            raise ValueError(f"table.capacity must be >= 1 (table {self.name})")
        if self.max_bytes < 0:
            raise ValueError(f"table.max_bytes must be >= 0 (table {self.name})")
        if self.max_times_sampled < 0:
            raise ValueError(f"table.max_times_sampled must be >= 0 (table {self.name})")
        self.rate_limiter.validate()

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TableConfig:
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"table config has unknown keys {sorted(unknown)}")
        d = dict(d)
        if isinstance(d.get("rate_limiter"), dict):
            d["rate_limiter"] = RateLimiterConfig(**d["rate_limiter"])
        return cls(**d)


def default_tables() -> tuple[TableConfig, ...]:
    """EM-CAC's pair: a 32-episode cycling buffer (K = 8) and a 5000-episode replay within
    DEFAULT_REPLAY_MAX_BYTES."""
    return (
        TableConfig(name="cycling", kind="cycling", capacity=32, max_times_sampled=8),
        TableConfig(
            name="replay", kind="replay", capacity=5000, max_bytes=DEFAULT_REPLAY_MAX_BYTES
        ),
    )


@dataclass(frozen=True)
class BufferConfig:
    """The buffer server.

    Attributes:
        host: bind address; anything but a loopback address requires ``token``.
        port: TCP port (0 = pick a free one; the server reports it).
        token: shared secret checked in hello (None = no auth, loopback only).
        tables: the tables; an insert naming no tables goes to all of them.
        schema: episode sizes; None = learned from the first hello that carries one.
        max_frame_bytes: largest request frame accepted; refused from its length prefix.
        snapshot_dir: where the log and snapshots live (None = in memory only, no
            durability).
        fsync: fsync the log before acknowledging an insert (False survives a kill -9 of
            the service, because written data sits in the OS page cache, but not a power
            loss or kernel crash).
        snapshot_every_inserts: write a snapshot (and truncate the log) after this many
            logged insert requests (0 = only on the snapshot op and on shutdown).
        snapshot_every_bytes: also write one once the log holds this many bytes (0 = no
            byte trigger), bounding the log's disk use and the restart's replay.
        sample_timeout_s: longest a sample waits for the rate limiter (requests may ask
            for less).
        insert_timeout_s: longest an insert waits for the rate limiter.
        read_timeout_s: a started frame (request or reply) must be transferred completely
            within this time, else the connection is aborted (its buffers freed).
        idle_timeout_s: an authenticated connection idle between frames for longer is
            closed (the project's BufferClient reconnects transparently).
        hello_timeout_s: a new connection must complete its hello within this time.
        max_connections: concurrent connections; when full, a new one takes the place of
            the oldest connection that has not completed its hello, else it is closed at once.
        max_unauthenticated: connections that have not completed their hello; a new one
            beyond this closes the oldest of them (so stalled sockets cannot lock clients
            out); the other max_connections - max_unauthenticated slots are reserved for
            authenticated connections.
        max_connections_per_client: authenticated connections of one client (the ``client``
            id of its hello); a hello beyond it is refused with ``too_many_connections``.
        max_hello_bytes: largest frame accepted before a hello succeeded.
        max_inflight_bytes: request bodies larger than max_hello_bytes that are read and
            handled at once, and sample replies being written, in bytes over all
            connections (further ones wait): beside the stored episodes, the server's
            memory is this plus about 1 MiB of socket buffers per connection.
        max_inflight_bytes_per_client: the share of max_inflight_bytes one client may hold
            (a larger sample reply is refused), so slow readers of one client cannot take
            every other client's share.
        max_sample_episodes: largest batch_size of one sample request.
        repair: on start, keep what a damaged snapshot_dir still holds and discard the rest
            (saying what), accepting acknowledged episodes that are missing, instead of
            refusing to start.
        dedup_window: per actor, how many episode_seq values are remembered exactly; seqs
            further behind the actor's window are treated as already inserted.
        metrics_port: Prometheus HTTP port on 127.0.0.1 (None = no exporter, 0 = any).
        seed: seed of the sampling RNG (None = from os.urandom); a launcher that wants a
            repeatable run sets it.
        store_state: keep each episode's global state (False: dropped on insert, for
            learners that never read it, `learner.registry.AlgoSpec.reads_state`).
    """

    host: str = "127.0.0.1"
    port: int = 0
    token: str | None = None
    tables: tuple[TableConfig, ...] = field(default_factory=default_tables)
    schema: EpisodeSchema | None = None
    max_frame_bytes: int = 64 * 2**20
    snapshot_dir: str | None = None
    fsync: bool = True
    snapshot_every_inserts: int = 10_000
    snapshot_every_bytes: int = 1 << 30
    sample_timeout_s: float = 30.0
    insert_timeout_s: float = 30.0
    read_timeout_s: float = 30.0
    idle_timeout_s: float = 300.0
    hello_timeout_s: float = 10.0
    max_connections: int = 512
    max_unauthenticated: int = 256
    max_connections_per_client: int = 32
    max_hello_bytes: int = 64 * 1024
    max_inflight_bytes: int = 256 * 2**20
    max_inflight_bytes_per_client: int = 128 * 2**20
    max_sample_episodes: int = 1024
    repair: bool = False
    dedup_window: int = 1 << 16
    metrics_port: int | None = None
    seed: int | None = None
    store_state: bool = True

    def validate(self) -> None:
        if not is_loopback(self.host) and not self.token:
            raise ValueError(f"host {self.host!r} is not loopback: a token is required to bind it")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port {self.port} outside 0..65535")
        if not self.tables:
            raise ValueError("tables must name at least one table")
        names = [t.name for t in self.tables]
        if len(set(names)) != len(names):
            raise ValueError(f"tables has duplicate names {names}")
        for t in self.tables:
            t.validate()
        if self.max_frame_bytes < 1024:
            raise ValueError("max_frame_bytes must be >= 1024")
        timeouts = ("sample_timeout_s", "insert_timeout_s", "read_timeout_s", "hello_timeout_s")
        for name in (*timeouts, "idle_timeout_s"):
            if not 0 < getattr(self, name) < math.inf:
                raise ValueError(f"{name} must be a finite number > 0")
        if not 1024 <= self.max_hello_bytes <= self.max_frame_bytes:
            raise ValueError("max_hello_bytes must be in 1024..max_frame_bytes")
        if self.max_inflight_bytes < self.max_frame_bytes:
            raise ValueError("max_inflight_bytes must be >= max_frame_bytes")
        per_client = self.max_inflight_bytes_per_client
        if not self.max_frame_bytes <= per_client <= self.max_inflight_bytes:
            raise ValueError(
                "max_inflight_bytes_per_client must be in max_frame_bytes..max_inflight_bytes"
            )
        if self.max_unauthenticated < 1:
            raise ValueError("max_unauthenticated must be >= 1")
        if self.max_connections_per_client < 1:
            raise ValueError("max_connections_per_client must be >= 1")
        if self.snapshot_every_bytes < 0:
            raise ValueError("snapshot_every_bytes must be >= 0")
        if self.max_sample_episodes < 1:
            raise ValueError("max_sample_episodes must be >= 1")
        if self.snapshot_every_inserts < 0:
            raise ValueError("snapshot_every_inserts must be >= 0")
        if self.max_connections < 1:
            raise ValueError("max_connections must be >= 1")
        if self.dedup_window < 16:
            raise ValueError("dedup_window must be >= 16")
        if self.metrics_port is not None and not 0 <= self.metrics_port <= 65535:
            raise ValueError(f"metrics_port {self.metrics_port} outside 0..65535")


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and ``localhost``."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
