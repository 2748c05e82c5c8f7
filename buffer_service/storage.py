"""Durability: an append-only log plus snapshots that compact it, all checksummed.

Guarantee: when ``BufferConfig.fsync`` is true (the default) an insert is acknowledged only
after its log record was written *and fsynced*, so an acknowledged episode survives a kill
-9 of the service, a kernel crash and a power loss (as far as the disk honours fsync). The
server commits in groups: one fsync covers every record written before it started, so
concurrent inserts share fsyncs instead of queueing one each. With ``fsync=False`` the
record is still written (handed to the kernel) before the ack, which survives a kill -9 of
the process but not a power loss. Sample records (which episodes were sampled, so a cycling
table's at-most-K count and retirements survive too) are written but not fsynced: after a
power loss an episode may be served a few more times than K, never lost or duplicated.
The exact guarantee per setting, with the commit file (`buffer_service.commit`):

* ``fsync=True``: an acknowledged insert's record was fsynced (with every record before
  it) and its high-water mark written to ``commit.bin``. It survives kill -9, a kernel
  crash and a power loss. A log later cut short or deleted (before its mark) is refused at
  restart and by `credit buffer verify`, naming the file and the episodes missing; after a
  power loss the mark itself may be a few commits old (it is fsynced per log generation,
  not per commit), so only then can a cut within those last commits go unnoticed.
* ``fsync=False``: an acknowledged insert's record and its mark were written (to the page
  cache): it survives kill -9 of the service, not a kernel crash or power loss, and after
  one the restart refuses (rightly: acknowledged episodes are gone) until told to accept it.

Disk full: an append that cannot be written completely is truncated back to the end of the
last complete record before anything is acknowledged (`WriteError`, code ``storage_full``),
so the log never holds a partial record in front of later ones; once space returns appends
go on after it. A failed fsync is not retried (the kernel may have dropped the pages): the
storage refuses every write until the service is restarted.

Files in ``snapshot_dir`` (record format: `buffer_service.records`), all created 0644::

    snapshot-g.bin   the state at the moment log-g was started (there is no snapshot-0)
    log-g.bin        records appended since; the state is snapshot-s + log-s + ... + log-top

A snapshot switches the log to generation g+1 first (on the event loop, cheap), then writes
``snapshot-(g+1).bin.tmp`` from a copy of the state's references in a thread, fsyncs and
renames it. The previous snapshot and the logs from it on are kept, so that a damaged newest
snapshot falls back to the previous one plus the logs; older generations are removed. A crash
at any point leaves a folder that restores completely: restart removes ``*.tmp`` files and
generations that are no longer needed.

Restore reads files record by record (memory: the largest record, not the file), the newest
intact snapshot (or, failing that, an older one or the empty state
when every log from generation 0 is still there) and replays the logs after it. A record that
is damaged (checksum, unreadable header; see `records`) is reported with its file and offset
and skipped, and the records after it are still read. The service refuses to start when
anything acknowledged may be missing (damaged records, no usable snapshot), naming the files,
or a log is shorter than its high-water mark or missing, unless started with ``repair``
(accepting the loss): then it keeps what can be read, says what it discarded,
renames the damaged files ``*.damaged`` and writes a fresh snapshot. A torn tail (an append
cut short by a crash, never acknowledged) is truncated with a warning. Format-1 folders
(before checksummed headers) are read and converted by a snapshot at once.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import os
import re
import threading
from typing import Any

from buffer_service import commit, records, snapshots
from buffer_service.config import TableConfig
from buffer_service.episode import EpisodeSchema
from buffer_service.records import FILE, INSERT, SAMPLE, SCHEMA
from buffer_service.restore import TEMP, RestoreMixin, StorageError
from buffer_service.snapshots import FILE_MODE
from buffer_service.state import BufferState, StateCopy

__all__ = ["NAME", "TEMP", "Storage", "StorageError", "WriteError"]

log = logging.getLogger(__name__)

NAME = re.compile(r"^(snapshot|log)-(\d{8})\.bin$")


class WriteError(RuntimeError):
    """A write to the folder failed and was rolled back; `code` is ``storage_full`` (no space
    or quota left) or ``internal``; nothing of the failed record stays in the log."""

    def __init__(self, message: str, err: OSError | None = None) -> None:
        super().__init__(message)
        full = err is not None and err.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
        self.code = "storage_full" if full else "internal"


class Storage(RestoreMixin):
    """Log, snapshots and commit file in one directory.

    Args:
        directory: the snapshot dir (created if missing).
        fsync: fsync every insert record before it is acknowledged (the server's
            GroupCommit waits for it; this class only records and syncs).
        repair: on restore, keep what can be read instead of refusing to start (accepting
            the loss of acknowledged episodes that are missing).
        tables: the table configs, recorded in every file (for `verify`).
        read_only: restore only (`credit buffer verify`): nothing is written, truncated,
            renamed or removed, and no log is opened.
    """

    def __init__(
        self,
        directory: str,
        fsync: bool = True,
        repair: bool = False,
        tables: tuple[TableConfig, ...] = (),
        read_only: bool = False,
    ) -> None:
        self.dir = directory
        self.fsync = fsync
        self.repair = repair
        self.read_only = read_only
        self.tables_meta = [dataclasses.asdict(t) for t in tables]
        self.gen = 0  # the generation of the log being appended to
        self.base = 0  # the newest complete snapshot (0: the empty state before log-0)
        self.fd: int | None = None
        self.records_since_snapshot = 0
        self.written = 0  # insert records appended by this process (see append_insert)
        self.size = 0  # bytes of the log being appended to (all complete records)
        self.episodes = 0  # episodes its insert records carry
        self.marks: commit.Marks = {}  # final (bytes, episodes) of the logs switched away from
        self.failed: str | None = None  # why nothing more may be written (a failed fsync)
        self.commit = commit.CommitFile(directory)
        self._tail = (0, 0, 0, 0)  # (gen, written, size, episodes), replaced in one assignment
        self._marked = self._tail  # the tail commit.bin records for the current log
        self._retired: list[int] = []  # logs switched away from, fsynced by the next sync
        self._dir_dirty = False  # a new log's directory entry awaits an fsync
        self._fd_lock = threading.Lock()  # `sync` (any thread) vs switching/closing the log
        if not read_only:
            os.makedirs(directory, exist_ok=True)

    write_error = WriteError  # (for RestoreMixin)

    def path(self, kind: str, gen: int) -> str:
        return os.path.join(self.dir, f"{kind}-{gen:08d}.bin")

    def _fsync_dir(self) -> None:
        fd = os.open(self.dir, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def generations(self) -> tuple[set[int], set[int]]:
        """(snapshot generations, log generations) present in the folder."""
        found: dict[str, set[int]] = {"snapshot": set(), "log": set()}
        for name in os.listdir(self.dir) if os.path.isdir(self.dir) else ():
            m = NAME.match(name)
            if m:
                found[m.group(1)].add(int(m.group(2)))
        return found["snapshot"], found["log"]

    def _retain(self, snapshots: set[int], min_log: int) -> None:
        """Remove every snapshot not in `snapshots` and every log older than `min_log`."""
        snaps, logs = self.generations()
        doomed = [self.path("snapshot", g) for g in snaps - snapshots]
        doomed += [self.path("log", g) for g in logs if g < min_log and g != self.gen]
        with self._fd_lock:
            self.marks = {g: m for g, m in self.marks.items() if g >= min_log}
        for path in doomed:
            os.remove(path)

    # ---------------------------------------------------------------- the log

    def _file_meta(self, role: str, gen: int, schema: EpisodeSchema | None) -> dict[str, Any]:
        return {
            "format": records.FORMAT,
            "role": role,
            "generation": gen,
            "tables": self.tables_meta,
            "schema": schema.to_dict() if schema else None,
            "commit": commit.NAME,
        }

    def _open_log(self, gen: int, schema: EpisodeSchema | None, episodes: int = 0) -> int:
        """Append to log-`gen` from now on (a new one gets its FILE record; on a full disk
        it is removed again and WriteError raised, the current log staying in use)."""
        path = self.path("log", gen)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, FILE_MODE)
        except OSError as e:
            raise WriteError(f"cannot create {path}: {e}", e) from None
        if os.fstat(fd).st_size == 0:
            try:
                records.write(fd, FILE, self._file_meta("log", gen, schema))
            except OSError as e:
                os.close(fd)
                os.remove(path)
                raise WriteError(f"cannot start {path}: {e}", e) from None
        size = os.fstat(fd).st_size
        with self._fd_lock:
            old, self.fd = self.fd, fd
            if old is not None:
                self._retired.append(old)
                self.marks[self.gen] = (self.size, self.episodes)
            if not self.fsync:
                for f in self._retired:
                    os.close(f)
                self._retired.clear()
            self._dir_dirty = True
            self.gen, self.size, self.episodes = gen, size, episodes
            self._tail = (gen, self.written, size, episodes)
        return fd

    def _append(self, kind: bytes, meta: Any, body: bytes | bytearray = b"") -> None:
        """Append one record, or none of it: a failed write is truncated away (WriteError)."""
        if self.failed:
            raise WriteError(f"{self.dir}: no more writes: {self.failed}")
        assert self.fd is not None
        start = self.size
        try:
            n = records.write(self.fd, kind, meta, body)
        except OSError as e:
            try:
                os.ftruncate(self.fd, start)
            except OSError as e2:
                self.failed = f"a failed append could not be rolled back ({e2}); restart"
                raise WriteError(f"{self.dir}: {e}; {self.failed}", e) from None
            name = f"log-{self.gen:08d}.bin"
            log.warning("%s: append failed (%s); rolled back to byte %d", name, e, start)
            raise WriteError(f"{name}: {e.strerror or e}: nothing stored", e) from None
        self.size = start + n

    def append_insert(self, tables: list[str], body: bytes | bytearray, episodes: int = 0) -> int:
        """Append an insert request (its raw, already validated frame body, carrying
        `episodes`), handed to the kernel but not fsynced; returns its number, durable once
        `sync` reaches it. WriteError when it could not be written (then nothing was)."""
        self._append(INSERT, {"tables": tables}, body)
        self.records_since_snapshot += 1
        self.written += 1
        self.episodes += episodes
        self._tail = (self.gen, self.written, self.size, self.episodes)
        if not self.fsync:  # acknowledged once written: so is its mark
            self.write_marks(tail=self._tail)
        return self.written

    def write_marks(self, sync: bool = False, tail: tuple[int, int, int, int] | None = None):
        """Record in commit.bin the logs' high-water marks: the current log's up to `tail`
        (durable or, with fsync=False, written), else as last recorded; never lowered."""
        with self._fd_lock:
            if tail is not None and tail[:3] > self._marked[:3]:
                self._marked = tail
            gen, _, size, episodes = self._marked
            marks = dict(self.marks)
            if gen not in marks:  # (a retired log's entry is its final size)
                marks[gen] = (size, episodes)
        self.commit.write(marks, sync=sync)

    def sync(self) -> int:
        """fsync the log (and a log switched away from since, and the folder after a switch),
        then write the marks; returns the number of the last insert record now durable. Safe
        to call from another thread while records are appended. WriteError when an fsync
        failed: the storage then refuses every write until restarted."""
        if self.failed:
            raise WriteError(f"{self.dir}: no more writes: {self.failed}")
        try:
            with self._fd_lock:
                assert self.fd is not None
                tail = self._tail
                self._sync_retired()
                os.fsync(self.fd)
                if self._dir_dirty:
                    self._fsync_dir()
                    self._dir_dirty = False
            self.write_marks(tail=tail)
        except OSError as e:
            self.failed = f"fsync failed ({e}); restart the service"
            raise WriteError(f"{self.dir}: {self.failed}", e) from None
        return tail[1]

    def _sync_retired(self) -> None:
        for fd in self._retired:
            os.fsync(fd)
            os.close(fd)
        self._retired.clear()

    def sync_retired(self) -> None:
        """fsync the logs switched away from (before their final marks are made durable)."""
        with self._fd_lock:
            self._sync_retired()

    def log_sample(self, table: str, keys: list[tuple[int, int]]) -> None:
        """Append which keys a sample took (written, not fsynced); WriteError when it could
        not be (then nothing was)."""
        self._append(SAMPLE, {"table": table, "keys": [list(k) for k in keys]})
        self._tail = (self.gen, self.written, self.size, self.episodes)

    def log_schema(self, schema: EpisodeSchema) -> None:
        self._append(SCHEMA, schema.to_dict())
        self._tail = (self.gen, self.written, self.size, self.episodes)
        self.sync()

    # ---------------------------------------------------------------- snapshots

    def begin_snapshot(self, state: BufferState) -> SnapshotJob:
        """Start generation g+1: copy the state's references and switch the log (cheap; on
        the event loop). The returned job's `write` produces the snapshot file (any thread).
        WriteError when the new log cannot be started (the current one stays in use)."""
        copy = state.capture()
        new = self.gen + 1
        self._open_log(new, state.schema)
        self.records_since_snapshot = 0
        return SnapshotJob(self, new, copy)

    def snapshot(self, state: BufferState) -> str:
        """Write generation g+1 from `state` now (blocking)."""
        return self.begin_snapshot(state).write()

    def _finish_snapshot(self, gen: int, copy: StateCopy) -> str:
        """Write snapshot `gen` from `copy`, make it the base and drop what it replaces."""
        final = self.path("snapshot", gen)
        snapshots.write_file(final, self._file_meta("snapshot", gen, copy.schema), copy)
        self._fsync_dir()
        previous, self.base = self.base, gen
        self._retain({gen, previous}, previous)  # the previous one stays as a fallback
        if self.commit.fd is not None:
            self.sync_retired()
            self.write_marks(sync=True)  # without the marks of the logs just removed
        log.info("snapshot %s: %d episodes", final, len(copy.episodes))
        return final

    def close(self) -> None:
        with self._fd_lock:
            for fd in [*self._retired, self.fd]:
                if fd is not None:
                    if self.fsync and not self.failed:
                        os.fsync(fd)
                    os.close(fd)
            self._retired.clear()
            self.fd = None
        if self.commit.fd is not None:
            if not self.failed:
                self.write_marks(sync=True)
            self.commit.close()


@dataclasses.dataclass(frozen=True)
class SnapshotJob:
    """Writes one snapshot from a `StateCopy` (`write`, in any thread); made by
    `Storage.begin_snapshot`."""

    storage: Storage
    gen: int
    copy: StateCopy

    def write(self) -> str:
        return self.storage._finish_snapshot(self.gen, self.copy)
