"""Durability: an append-only log plus periodic snapshots that compact it.

Guarantee: when ``BufferConfig.fsync`` is true (the default) an insert is acknowledged only
after its log record was written *and fsynced*, so an acknowledged episode survives a kill
-9 of the service, a kernel crash and a power loss (as far as the disk honours fsync). The
server commits in groups: one fsync covers every record written before it started, so
concurrent inserts share fsyncs instead of queueing one each. With
``fsync=False`` the record is still written (handed to the kernel) before the ack, which
survives a kill -9 of the process but not a power loss. Sample records (which episodes were
sampled, so a cycling table's at-most-K count and retirements survive too) are written but
not fsynced: after a power loss an episode may be served a few more times than K, never
lost or duplicated.

Files in ``snapshot_dir`` (generation g)::

    snapshot-g.bin   full state at the moment log-g was started (absent for g = 0)
    log-g.bin        records appended since

A record is ``[u32 payload length][u32 crc32 of payload][u8 kind][u32 meta length]``
followed by the payload ``meta (msgpack) + body``. Restore reads the newest complete
snapshot, then replays its log up to the first torn or corrupt record (a crash mid-append)
and truncates the log there. A snapshot is written to a temporary file, fsynced and
renamed, so a crash while snapshotting leaves the previous generation intact.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import struct
import threading
import zlib
from typing import Any

import msgpack

from buffer_service import codec
from buffer_service.episode import EpisodeSchema
from buffer_service.state import BufferState

log = logging.getLogger(__name__)

RECORD = struct.Struct(">IIBI")
INSERT, SAMPLE, SCHEMA, HEADER, EPISODE, END = b"I", b"S", b"C", b"H", b"E", b"Z"
_NAME = re.compile(r"^(snapshot|log)-(\d{8})\.bin$")


def _pack_meta(meta: Any) -> bytes:
    return msgpack.packb(meta, use_bin_type=True)


def _write_record(fd: int, kind: bytes, meta: Any, body: bytes = b"") -> None:
    m = _pack_meta(meta)
    crc = zlib.crc32(body, zlib.crc32(m))
    head = RECORD.pack(len(m) + len(body), crc, kind[0], len(m))
    parts = [head, m, body] if body else [head, m]
    total = sum(len(p) for p in parts)
    done = os.writev(fd, parts)
    if done != total:  # short write (rare on regular files): finish it by hand
        rest = b"".join(bytes(p) for p in parts)[done:]
        while rest:
            rest = rest[os.write(fd, rest) :]


def read_records(path: str) -> tuple[list[tuple[bytes, Any, memoryview]], int]:
    """All intact records of `path` and the byte offset where they end."""
    with open(path, "rb") as f:
        data = f.read()
    view = memoryview(data)
    out, pos = [], 0
    while pos + RECORD.size <= len(data):
        length, crc, kind, mlen = RECORD.unpack_from(data, pos)
        start, end = pos + RECORD.size, pos + RECORD.size + length
        if end > len(data) or mlen > length:
            break
        payload = view[start:end]
        if zlib.crc32(payload) != crc:
            break
        meta = msgpack.unpackb(payload[:mlen], raw=False, strict_map_key=False)
        out.append((bytes([kind]), meta, payload[mlen:]))
        pos = end
    return out, pos


class Storage:
    """Log and snapshots in one directory.

    Args:
        directory: the snapshot dir (created if missing).
        fsync: fsync every insert record before it is acknowledged (the server's
            GroupCommit waits for it; this class only records and syncs).
    """

    def __init__(self, directory: str, fsync: bool = True) -> None:
        self.dir = directory
        self.fsync = fsync
        self.gen = 0
        self.fd: int | None = None
        self.records_since_snapshot = 0
        self.written = 0  # insert records appended by this process (see append_insert)
        self._fd_lock = threading.Lock()  # `sync` (any thread) vs switching/closing the log
        os.makedirs(directory, exist_ok=True)

    def _path(self, kind: str, gen: int) -> str:
        return os.path.join(self.dir, f"{kind}-{gen:08d}.bin")

    def _fsync_dir(self) -> None:
        fd = os.open(self.dir, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def restore(self, state: BufferState) -> dict[str, int]:
        """Load the newest snapshot and replay its log into `state`; open the log."""
        gens = {}
        for name in os.listdir(self.dir):
            m = _NAME.match(name)
            if m:
                gens.setdefault(m.group(1), []).append(int(m.group(2)))
        self.gen, n_eps = 0, 0
        for g in sorted(gens.get("snapshot", []), reverse=True):
            n = self._load_snapshot(g, state)
            if n is not None:
                self.gen, n_eps = g, n
                break
            log.error("snapshot %s is incomplete; trying an older one", self._path("snapshot", g))
        n_rec, torn = self._replay_log(state)
        self.fd = os.open(self._path("log", self.gen), os.O_WRONLY | os.O_CREAT | os.O_APPEND)
        self._fsync_dir()
        info = {"generation": self.gen, "snapshot_episodes": n_eps, "log_records": n_rec}
        info["torn_bytes"] = torn
        log.info("restored buffer from %s: %s", self.dir, info)
        return info

    def _load_snapshot(self, gen: int, state: BufferState) -> int | None:
        records, _ = read_records(self._path("snapshot", gen))
        if not records or records[0][0] != HEADER or records[-1][0] != END:
            return None
        state.episodes = {}
        for kind, _meta, body in records[1:-1]:
            if kind == EPISODE:
                ep = codec.own(codec.episode_from_wire(codec.unpack(body)))
                state.episodes[ep.key] = ep
        state.load_header(records[0][1])
        state.rebuild_refs()
        return len(state.episodes)

    def _replay_log(self, state: BufferState) -> tuple[int, int]:
        path = self._path("log", self.gen)
        if not os.path.exists(path):
            return 0, 0
        records, end = read_records(path)
        for kind, meta, body in records:
            if kind == INSERT:
                msg = codec.unpack(body)
                for wire in msg["episodes"]:
                    state.insert(codec.own(codec.episode_from_wire(wire)), meta["tables"])
            elif kind == SAMPLE:
                if meta["table"] in state.tables:
                    state.apply_sample(meta["table"], [tuple(k) for k in meta["keys"]])
            elif kind == SCHEMA:
                state.schema = EpisodeSchema.from_dict(meta)
        size = os.path.getsize(path)
        if end < size:
            log.warning("log %s has a torn tail of %d bytes; truncating", path, size - end)
            with open(path, "r+b") as f:
                f.truncate(end)
                os.fsync(f.fileno())
        self.records_since_snapshot = len(records)
        return len(records), size - end

    def append_insert(self, tables: list[str], body: bytes) -> int:
        """Append an insert request (its raw, already validated frame body), handed to the
        kernel but not fsynced; returns its number, durable once `synced` reaches it."""
        assert self.fd is not None
        _write_record(self.fd, INSERT, {"tables": tables}, body)
        self.records_since_snapshot += 1
        self.written += 1
        return self.written

    def sync(self) -> int:
        """fsync the log; returns the number of the last insert record now durable. Safe to
        call from another thread while records are appended; a snapshot waits for it (its
        log may be the one the snapshot retires: the records in it are then in the snapshot)."""
        with self._fd_lock:
            assert self.fd is not None
            upto = self.written
            os.fsync(self.fd)
            return upto

    def log_sample(self, table: str, keys: list[tuple[int, int]]) -> None:
        """Append which keys a sample took (written, not fsynced)."""
        assert self.fd is not None
        _write_record(self.fd, SAMPLE, {"table": table, "keys": [list(k) for k in keys]})

    def log_schema(self, schema: EpisodeSchema) -> None:
        assert self.fd is not None
        _write_record(self.fd, SCHEMA, schema.to_dict())
        os.fsync(self.fd)

    def snapshot(self, state: BufferState) -> str:
        """Write generation g+1 from `state`, switch the log to it and drop generation g."""
        new = self.gen + 1
        final, tmp = self._path("snapshot", new), self._path("snapshot", new) + ".tmp"
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_record(fd, HEADER, state.header_state())
            for ep in state.episodes.values():
                _write_record(fd, EPISODE, None, codec.pack(codec.episode_to_wire(ep)))
            _write_record(fd, END, None)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, final)
        new_fd = os.open(self._path("log", new), os.O_WRONLY | os.O_CREAT | os.O_APPEND)
        self._fsync_dir()
        with self._fd_lock:
            old, self.gen = self.gen, new
            if self.fd is not None:
                os.close(self.fd)
            self.fd = new_fd
        self.records_since_snapshot = 0
        for kind in ("log", "snapshot"):
            with contextlib.suppress(FileNotFoundError):
                os.remove(self._path(kind, old))
        log.info("snapshot %s: %d episodes", final, len(state.episodes))
        return final

    def close(self) -> None:
        with self._fd_lock:
            if self.fd is not None:
                os.close(self.fd)
                self.fd = None
