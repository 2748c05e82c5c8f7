"""How far the acknowledged log extends: the commit file, and the group commit that feeds it.

A log cannot tell by itself that records were cut from its end or that it was deleted, so the
service records beside it, in ``commit.bin``, the *high-water mark* of every log it still
needs: ``generation -> (bytes, episodes)``, how many bytes of the log were made durable
(fsync=True) or written (fsync=False) before anything in them was acknowledged, and how many
episodes the insert records in those bytes carry (as Kafka's replication-offset checkpoint
and etcd's commit index do). Restore refuses a log that ends before its mark or is missing,
naming the file and how many acknowledged episodes are gone (`storage.Storage.restore`),
unless told to accept the loss; bytes after the mark are a crash's torn tail and stay
accepted.

Cost: one ``pwrite`` of a few dozen bytes per group commit (per insert with fsync=False),
into a file of two fixed slots (no allocation, so it works on a full disk too). The file is
fsynced when a log generation is opened or retired, after a snapshot and on close, not per
commit: the mark is in the page cache when the insert is acknowledged, so it survives a kill
-9 of the service; after a power loss it may be older than the log (never newer: it is
written after the log's fsync), which weakens the check for the last few seconds and never
refuses a complete log.

Layout: two slots of `SLOT` bytes, each ``magic | u32 length | u32 crc32 | msgpack {"seq",
"marks": [[generation, bytes, episodes], ...]}``; a write goes to slot ``seq % 2`` so that a
torn write leaves the other slot intact, and a reader takes the intact slot with the
highest ``seq``.
"""

from __future__ import annotations

import asyncio
import os
import struct
import threading
import zlib
from typing import TYPE_CHECKING

import msgpack

if TYPE_CHECKING:  # storage imports this module
    from buffer_service.storage import Storage

NAME = "commit.bin"
SLOT = 4096
MAGIC = b"\xd7CRm"
HEAD = struct.Struct(">4sII")

Marks = dict[int, tuple[int, int]]  # generation -> (acknowledged bytes, episodes in them)


class CommitFileError(ValueError):
    """Neither slot of the commit file is intact."""


class CommitFile:
    """``commit.bin`` in `directory`: `read` the marks, `write` new ones (cheap), `sync`."""

    def __init__(self, directory: str) -> None:
        self.path = os.path.join(directory, NAME)
        self.fd: int | None = None
        self.seq = 0
        self._lock = threading.Lock()  # writers: the event loop, fsync and snapshot threads

    def read(self) -> Marks | None:
        """The newest intact marks; None when there is no file; CommitFileError when
        neither slot is intact."""
        try:
            with open(self.path, "rb") as f:
                data = f.read(2 * SLOT)
        except FileNotFoundError:
            return None
        best: tuple[int, Marks] | None = None
        for i in range(2):
            slot = _parse(data[i * SLOT : (i + 1) * SLOT])
            if slot is not None and (best is None or slot[0] > best[0]):
                best = slot
        if best is None:
            if not data.strip(b"\0"):
                return {}  # created, never written: nothing was acknowledged
            raise CommitFileError(f"{NAME}: neither slot is intact")
        self.seq = best[0]
        return best[1]

    def open(self, fsync_dir) -> None:
        """Open for writing; a new file gets its two slots (zeros) allocated and fsynced."""
        fresh = not os.path.exists(self.path)
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        if fresh or os.fstat(self.fd).st_size < 2 * SLOT:
            os.ftruncate(self.fd, 2 * SLOT)
            os.pwrite(self.fd, bytes(2 * SLOT), 0)
            os.fsync(self.fd)
            fsync_dir()

    def write(self, marks: Marks, sync: bool = False) -> None:
        assert self.fd is not None
        listed = [[g, b, e] for g, (b, e) in sorted(marks.items())]
        with self._lock:
            self.seq += 1
            body = msgpack.packb({"seq": self.seq, "marks": listed})
            if HEAD.size + len(body) > SLOT:
                raise ValueError(f"{len(marks)} marks do not fit a commit slot")
            head = HEAD.pack(MAGIC, len(body), zlib.crc32(body))
            os.pwrite(self.fd, head + body, (self.seq % 2) * SLOT)
            if sync:
                os.fdatasync(self.fd)

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def _parse(slot: bytes) -> tuple[int, Marks] | None:
    if len(slot) < HEAD.size:
        return None
    magic, n, crc = HEAD.unpack_from(slot)
    body = slot[HEAD.size : HEAD.size + n]
    if magic != MAGIC or len(body) != n or zlib.crc32(body) != crc:
        return None
    try:
        d = msgpack.unpackb(body)
        return int(d["seq"]), {int(g): (int(b), int(e)) for g, b, e in d["marks"]}
    except (ValueError, KeyError, TypeError):
        return None


def shortfalls(marks: Marks, found: dict[int, tuple[int, int]], base: int) -> list[str]:
    """What the logs replayed from generation `base` on lack against their marks: one line
    per log that ends before its mark, naming it and the acknowledged episodes missing.
    (`found`: generation -> (intact bytes, episodes read, ...); missing logs are named by the
    restore itself, with `missing_note`.)"""
    out = []
    for g, (length, eps) in sorted(marks.items()):
        if g < base or g not in found:
            continue
        end, got = found[g][:2]
        if end < length:
            out.append(
                f"log-{g:08d}.bin ends at byte {end} but its first {length} bytes were "
                f"acknowledged ({NAME}): {max(eps - got, 0)} of {eps} acknowledged episodes "
                "are missing (the log was truncated)"
            )
    return out


def missing_note(marks: Marks | None, gen: int) -> str:
    if marks is None or gen not in marks:
        return ""
    length, eps = marks[gen]
    return f" ({eps} acknowledged episodes in {length} bytes, per {NAME})"


class GroupCommit:
    """Acknowledge inserts once fsynced, with one fsync for every record written before it
    started. The fsync runs in a thread, so the event loop keeps taking requests meanwhile;
    with a single connection (nothing to group) it runs inline, saving the hand-off. A failed
    fsync raises `storage.WriteError` to every insert waiting for it (and the storage
    refuses writes from then on: what the kernel did with the data is unknown).

    Calling pattern (on the event loop)::

        n = storage.append_insert(tables, body, episodes)
        await commits.durable(n)        # returns once an fsync (or a snapshot) covered record n
        await commits.idle()            # no fsync in flight (before closing the storage)
    """

    def __init__(self, storage: Storage) -> None:
        self.storage = storage
        self.synced = 0  # the last record number an fsync (or a snapshot) made durable
        self.fsyncs = 0
        self._task: asyncio.Task | None = None

    async def durable(self, record: int, alone: bool = False) -> None:
        """Return once `record` is fsynced. `alone`: no other connection can write meanwhile,
        so there is nothing to group and the fsync runs here, without the thread hand-off."""
        if alone and self._task is None and self.synced < record:
            self.synced = max(self.synced, self.storage.sync())
            self.fsyncs += 1
        while self.synced < record:
            if self._task is None:
                self._task = asyncio.ensure_future(self._sync())
            await asyncio.shield(self._task)

    async def idle(self) -> None:
        while self._task is not None:
            await asyncio.gather(asyncio.shield(self._task), return_exceptions=True)

    async def _sync(self) -> None:
        try:
            upto = await asyncio.to_thread(self.storage.sync)
            self.synced = max(self.synced, upto)
            self.fsyncs += 1
        finally:
            self._task = None
