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

Files in ``snapshot_dir`` (record format: `buffer_service.records`), all created 0644::

    snapshot-g.bin   the state at the moment log-g was started (there is no snapshot-0)
    log-g.bin        records appended since; the state is snapshot-s + log-s + ... + log-top

A snapshot switches the log to generation g+1 first (on the event loop, cheap), then writes
``snapshot-(g+1).bin.tmp`` from a copy of the state's references in a thread, fsyncs and
renames it. The previous snapshot and the logs from it on are kept, so that a damaged newest
snapshot falls back to the previous one plus the logs; older generations are removed. A crash
at any point leaves a folder that restores completely: restart removes ``*.tmp`` files and
generations that are no longer needed.

Restore reads the newest intact snapshot (or, failing that, an older one or the empty state
when every log from generation 0 is still there) and replays the logs after it. A record that
is damaged (checksum, unreadable header; see `records`) is reported with its file and offset
and skipped, and the records after it are still read. The service refuses to start when
anything acknowledged may be missing (damaged records, no usable snapshot), naming the files,
unless started with ``repair``: then it keeps what can be read, says what it discarded,
renames the damaged files ``*.damaged`` and writes a fresh snapshot. A torn tail (an append
cut short by a crash, never acknowledged) is truncated with a warning. Format-1 folders
(before checksummed headers) are read and converted by a snapshot at once.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
import threading
from dataclasses import dataclass, field
from typing import Any

from buffer_service import codec, records
from buffer_service.codec import CodecError
from buffer_service.config import TableConfig
from buffer_service.episode import EpisodeError, EpisodeSchema
from buffer_service.records import EPISODE, FILE, HEADER, INSERT, SAMPLE, SCHEMA, Scan
from buffer_service.snapshots import FILE_MODE, SnapshotJob, describe, snapshot_problem
from buffer_service.state import BufferState

log = logging.getLogger(__name__)

NAME = re.compile(r"^(snapshot|log)-(\d{8})\.bin$")
TEMP = re.compile(r"^(snapshot|log)-(\d{8})\.bin\.tmp$")


class StorageError(RuntimeError):
    """The folder cannot be restored completely; the message names every damaged file."""


@dataclass
class _Restore:
    """What a restore found (see `Storage.restore`)."""

    snaps: set[int]
    logs: set[int]
    top: int
    base: int | None = None  # the snapshot restored from (0: the empty state)
    replayed: list[int] = field(default_factory=list)
    formats: set[int | None] = field(default_factory=set)
    torn: Scan | None = None  # of the newest log
    bad_snaps: list[int] = field(default_factory=list)
    damaged_logs: list[int] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # recovered from elsewhere: nothing lost
    losses: list[str] = field(default_factory=list)  # acknowledged data may be missing


class Storage:
    """Log and snapshots in one directory.

    Args:
        directory: the snapshot dir (created if missing).
        fsync: fsync every insert record before it is acknowledged (the server's
            GroupCommit waits for it; this class only records and syncs).
        repair: on restore, keep what can be read instead of refusing to start.
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
        self._retired: list[int] = []  # logs switched away from, fsynced by the next sync
        self._dir_dirty = False  # a new log's directory entry awaits an fsync
        self._fd_lock = threading.Lock()  # `sync` (any thread) vs switching/closing the log
        if not read_only:
            os.makedirs(directory, exist_ok=True)

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

    # ---------------------------------------------------------------- restore

    def restore(self, state: BufferState) -> dict[str, Any]:
        """Load the newest usable snapshot and replay the logs after it into `state`; open the
        log. Raises StorageError (naming files and offsets) when acknowledged data may be
        missing, unless `repair`. Returns what was read (generations, counts, problems)."""
        if not self.read_only:
            self._remove_temp_files()
        snaps, logs = self.generations()
        r = _Restore(snaps=snaps, logs=logs, top=max(snaps | logs, default=0))
        if snaps or logs:
            self._read(state, r)
        else:  # a new folder
            r.base = 0
        info = {"generation": r.top, "snapshot": r.base or None, "logs": r.replayed}
        info |= {"episodes": len(state.episodes), "warnings": r.warnings, "losses": r.losses}
        for w in r.warnings:
            log.warning("%s: %s", self.dir, w)
        if r.losses and not self.repair:
            raise StorageError(
                f"buffer folder {self.dir} cannot be restored completely: "
                + "; ".join(r.losses)
                + " (start with --repair to keep what can be read and discard the rest, or "
                "inspect it with `credit buffer verify`)"
            )
        if not self.read_only:
            for w in r.losses:
                log.error("%s: --repair discards: %s", self.dir, w)
            self._open_after_restore(state, r)
            log.info("restored buffer from %s: %s", self.dir, info)
        return info

    def _read(self, state: BufferState, r: _Restore) -> None:
        scan = self._choose_base(r)
        if r.base is None:
            r.losses.append("no intact snapshot with every log after it")
            scan = self._best_effort_base(r)
        if scan is not None:
            self._load_snapshot(scan, state, r)
            r.formats.add(scan.format)
        for g in range(r.base, r.top + 1):
            if g not in r.logs:
                if not g == r.base == r.top:  # (format 1 made a snapshot's log after it)
                    r.losses.append(f"log-{g:08d}.bin is missing")
                continue
            sc = self._replay_log(g, state, r)
            r.replayed.append(g)
            r.formats.add(sc.format)
            if sc.torn:
                r.torn = sc if g == r.top else r.torn
                off, size = sc.torn
                r.warnings.append(
                    f"log-{g:08d}.bin: torn tail of {size} bytes at offset {off} (an append cut "
                    "short by a crash, never acknowledged)"
                )

    def _choose_base(self, r: _Restore) -> Scan | None:
        """The newest intact snapshot with every log after it, else 0 (the empty state) when
        every log from log-0 on is there; sets r.base and returns the snapshot's scan."""
        for s in sorted(r.snaps, reverse=True):
            sc = records.scan_file(self.path("snapshot", s))
            why = snapshot_problem(sc)
            first = s if s < r.top else s + 1  # (format 1 made a snapshot's log after it)
            if why is None and all(g in r.logs for g in range(first, r.top + 1)):
                r.base = s
                return sc
            r.warnings.append(f"snapshot-{s:08d}.bin {why or 'lacks a later log'}; trying older")
            if why is not None:
                r.bad_snaps.append(s)
        if all(g in r.logs for g in range(0, r.top + 1)):
            r.base = 0
        return None

    def _best_effort_base(self, r: _Restore) -> Scan | None:
        """No usable snapshot (repair): the newest one whose header can be read, else none."""
        for s in sorted(r.snaps, reverse=True):
            sc = records.scan_file(self.path("snapshot", s))
            if any(rec.kind == HEADER for rec in sc.records):
                if sc.damaged or sc.torn:
                    r.losses.append(f"snapshot-{s:08d}.bin: {describe(sc) or 'cut short'}")
                r.base = s
                return sc
        r.base = min(r.logs, default=0)
        return None

    def _load_snapshot(self, scan: Scan, state: BufferState, r: _Restore) -> None:
        state.episodes = {}
        header = None
        for rec in scan.records:
            if rec.kind == EPISODE:
                try:
                    ep = codec.own(codec.episode_from_wire(codec.unpack(rec.body)))
                except CodecError as e:
                    r.losses.append(f"snapshot-{r.base:08d}.bin offset {rec.offset}: {e}")
                    continue
                state.episodes[ep.key] = ep
            elif rec.kind == HEADER and header is None:
                header = rec.meta
        state.load_header(header)
        state.rebuild_refs()

    def _replay_log(self, gen: int, state: BufferState, r: _Restore) -> Scan:
        name = f"log-{gen:08d}.bin"
        sc = records.scan_file(self.path("log", gen))
        if sc.damaged:
            r.losses.append(f"{name}: damaged records: {describe(sc)}")
            r.damaged_logs.append(gen)
        for rec in sc.records:
            try:
                self._apply(rec, state)
            except (CodecError, EpisodeError, KeyError, TypeError, ValueError) as e:
                r.losses.append(f"{name}: record at offset {rec.offset} is unreadable: {e}")
                r.damaged_logs.append(gen)
        self.records_since_snapshot = len(sc.records)
        return sc

    @staticmethod
    def _apply(rec: records.Record, state: BufferState) -> None:
        if rec.kind == INSERT:
            wires = codec.unpack(rec.body)["episodes"]
            eps = [codec.own(codec.episode_from_wire(w)) for w in wires]
            for ep in eps:  # all or nothing, as when it was inserted
                if state.schema is not None:
                    ep.validate(state.schema)
            for ep in eps:
                state.insert(ep, [t for t in rec.meta["tables"] if isinstance(t, str)])
        elif rec.kind == SAMPLE:
            if rec.meta["table"] in state.tables:
                state.apply_sample(rec.meta["table"], [tuple(k) for k in rec.meta["keys"]])
        elif rec.kind == SCHEMA:
            state.schema = EpisodeSchema.from_dict(rec.meta)
        elif rec.kind == FILE and state.schema is None and rec.meta.get("schema"):
            state.schema = EpisodeSchema.from_dict(rec.meta["schema"])

    def _open_after_restore(self, state: BufferState, r: _Restore) -> None:
        """Open the log to append to; after a fallback, a repair or format-1 files, write a
        fresh snapshot first; remove generations no longer needed."""
        self.gen, self.base = r.top, r.base
        if r.losses or r.bad_snaps or 1 in r.formats:
            for s in r.bad_snaps:
                self._set_aside(self.path("snapshot", s))
            for g in set(r.damaged_logs):
                self._set_aside(self.path("log", g))
            self.snapshot(state)  # log top+1 and snapshot top+1
            if r.losses:  # nothing older is restorable as it was: keep only the new one
                self._retain({self.base}, self.base)
            return
        if r.torn is not None:
            with open(self.path("log", r.top), "r+b") as f:
                f.truncate(r.torn.intact_end)
                os.fsync(f.fileno())
        self._open_log(r.top, state.schema)
        # The fallback to keep: the previous snapshot, or the empty state if log-0 is there.
        from_zero = all(g in r.logs for g in range(0, r.base))
        prev = max((s for s in r.snaps if s < r.base), default=0 if from_zero else r.base)
        self._retain({r.base, prev}, prev)

    def _set_aside(self, path: str) -> None:
        if os.path.exists(path):
            os.replace(path, path + ".damaged")
            log.error("%s set aside as %s.damaged", path, os.path.basename(path))

    def _remove_temp_files(self) -> None:
        for name in os.listdir(self.dir):
            if TEMP.match(name):
                os.remove(os.path.join(self.dir, name))
                log.info("removed %s, left by an interrupted snapshot", name)

    def _retain(self, snapshots: set[int], min_log: int) -> None:
        """Remove every snapshot not in `snapshots` and every log older than `min_log`."""
        snaps, logs = self.generations()
        doomed = [self.path("snapshot", g) for g in snaps - snapshots]
        doomed += [self.path("log", g) for g in logs if g < min_log and g != self.gen]
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
        }

    def _open_log(self, gen: int, schema: EpisodeSchema | None) -> int:
        path = self.path("log", gen)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, FILE_MODE)
        if os.fstat(fd).st_size == 0:
            records.write(fd, FILE, self._file_meta("log", gen, schema))
        with self._fd_lock:
            old, self.fd = self.fd, fd
            if old is not None:
                self._retired.append(old)
            if not self.fsync:
                for f in self._retired:
                    os.close(f)
                self._retired.clear()
            self._dir_dirty = True
        return fd

    def append_insert(self, tables: list[str], body: bytes | bytearray) -> int:
        """Append an insert request (its raw, already validated frame body), handed to the
        kernel but not fsynced; returns its number, durable once `synced` reaches it."""
        assert self.fd is not None
        records.write(self.fd, INSERT, {"tables": tables}, body)
        self.records_since_snapshot += 1
        self.written += 1
        return self.written

    def sync(self) -> int:
        """fsync the log (and a log switched away from since, and the folder after a switch);
        returns the number of the last insert record now durable. Safe to call from another
        thread while records are appended."""
        with self._fd_lock:
            assert self.fd is not None
            upto = self.written
            for fd in self._retired:
                os.fsync(fd)
                os.close(fd)
            self._retired.clear()
            os.fsync(self.fd)
            if self._dir_dirty:
                self._fsync_dir()
                self._dir_dirty = False
            return upto

    def log_sample(self, table: str, keys: list[tuple[int, int]]) -> None:
        """Append which keys a sample took (written, not fsynced)."""
        assert self.fd is not None
        records.write(self.fd, SAMPLE, {"table": table, "keys": [list(k) for k in keys]})

    def log_schema(self, schema: EpisodeSchema) -> None:
        assert self.fd is not None
        records.write(self.fd, SCHEMA, schema.to_dict())
        self.sync()

    # ---------------------------------------------------------------- snapshots

    def begin_snapshot(self, state: BufferState) -> SnapshotJob:
        """Start generation g+1: copy the state's references and switch the log (cheap; on
        the event loop). The returned job's `write` produces the snapshot file (any thread)."""
        copy = state.capture()
        new = self.gen + 1
        self._open_log(new, state.schema)
        self.gen = new
        self.records_since_snapshot = 0
        return SnapshotJob(self, new, copy)

    def snapshot(self, state: BufferState) -> str:
        """Write generation g+1 from `state` now (blocking)."""
        return self.begin_snapshot(state).write()

    def close(self) -> None:
        with self._fd_lock:
            for fd in [*self._retired, self.fd]:
                if fd is not None:
                    if self.fsync:
                        os.fsync(fd)
                    os.close(fd)
            self._retired.clear()
            self.fd = None
