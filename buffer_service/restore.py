"""Restoring the buffer's folder (`Storage.restore`, written as `RestoreMixin` so that the
storage module stays about its log): which snapshot to start from, replaying the logs after
it record by record, checking them against their high-water marks in ``commit.bin``, and
what is refused, warned about or repaired. The guarantee is `buffer_service.storage`'s."""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field
from typing import Any

from buffer_service import codec, commit, records
from buffer_service.codec import CodecError
from buffer_service.episode import EpisodeError, EpisodeSchema
from buffer_service.records import EPISODE, FILE, HEADER, INSERT, SAMPLE, SCHEMA, Scan
from buffer_service.snapshots import describe, snapshot_problem
from buffer_service.state import BufferState

log = logging.getLogger(__name__)

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
    marks: commit.Marks | None = None  # the commit file's high-water marks (None: no file)
    found: dict[int, tuple[int, int]] = field(default_factory=dict)  # gen -> (bytes, episodes)
    bad_snaps: list[int] = field(default_factory=list)
    damaged_logs: list[int] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # recovered from elsewhere: nothing lost
    losses: list[str] = field(default_factory=list)  # acknowledged data may be missing


class RestoreMixin:
    """`Storage.restore` and its steps (see the module docstring)."""

    def restore(self, state: BufferState) -> dict[str, Any]:
        """Load the newest usable snapshot and replay the logs after it into `state`; open the
        log. Raises StorageError (naming files and offsets) when acknowledged data may be
        missing, unless `repair`; WriteError when the folder cannot be written (a full disk).
        Returns what was read (generations, counts, problems)."""
        if not self.read_only:
            self._remove_temp_files()
        snaps, logs = self.generations()
        r = _Restore(snaps=snaps, logs=logs, top=max(snaps | logs, default=0))
        self._read_marks(r)
        if snaps or logs or r.marks:
            self._read(state, r)
            if r.marks is not None:
                r.losses += commit.shortfalls(r.marks, r.found, r.base or 0)
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
                + " (start with --repair to accept the loss, keep what can be read and "
                "discard the rest, or inspect it with `credit buffer verify`)"
            )
        if not self.read_only:
            for w in r.losses:
                log.error("%s: --repair discards: %s", self.dir, w)
            try:
                self._open_after_restore(state, r)
            except OSError as e:
                raise self.write_error(f"cannot write to {self.dir}: {e}", e) from None
            log.info("restored buffer from %s: %s", self.dir, info)
        return info

    def _read_marks(self, r: _Restore) -> None:
        try:
            r.marks = self.commit.read()
        except commit.CommitFileError as e:
            r.losses.append(f"{e}: how far the logs were acknowledged is unknown")
            r.marks = {}
        if r.marks:
            r.top = max(r.top, *r.marks)

    def _read(self, state: BufferState, r: _Restore) -> None:
        path = self._choose_base(r)
        if r.base is None:
            r.losses.append("no intact snapshot with every log after it")
            path = self._best_effort_base(r)
        if path is not None:
            self._load_snapshot(path, state, r)
        for g in range(r.base, r.top + 1):
            if g not in r.logs:
                # (format 1 made a snapshot's log after it: no log-g beside snapshot-g)
                if not g == r.base == r.top or commit.missing_note(r.marks, g):
                    r.losses.append(f"log-{g:08d}.bin is missing{commit.missing_note(r.marks, g)}")
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
        if r.marks is None and any(r.found[g][2] for g in r.found):
            r.losses.append(f"{commit.NAME} is missing, though the logs were written with one")

    def _choose_base(self, r: _Restore) -> str | None:
        """The newest intact snapshot with every log after it, else 0 (the empty state) when
        every log from log-0 on is there; sets r.base and returns the snapshot's path."""
        for s in sorted(r.snaps, reverse=True):
            path = self.path("snapshot", s)
            sc = records.scan_file(path, keep=False)
            why = snapshot_problem(sc)
            first = s if s < r.top else s + 1  # (format 1 made a snapshot's log after it)
            if why is None and all(g in r.logs for g in range(first, r.top + 1)):
                r.base = s
                r.formats.add(sc.format)
                return path
            r.warnings.append(f"snapshot-{s:08d}.bin {why or 'lacks a later log'}; trying older")
            if why is not None:
                r.bad_snaps.append(s)
        if all(g in r.logs for g in range(0, r.top + 1)):
            r.base = 0
        return None

    def _best_effort_base(self, r: _Restore) -> str | None:
        """No usable snapshot (repair): the newest one whose header can be read, else none."""
        for s in sorted(r.snaps, reverse=True):
            path = self.path("snapshot", s)
            sc = records.scan_file(path, keep=False)
            if sc.kinds.get(HEADER):
                if sc.damaged or sc.torn:
                    r.losses.append(f"snapshot-{s:08d}.bin: {describe(sc) or 'cut short'}")
                r.base = s
                return path
        r.base = min(r.logs, default=0)
        return None

    def _load_snapshot(self, path: str, state: BufferState, r: _Restore) -> None:
        state.episodes = {}
        header = None

        def load(rec: records.Record) -> None:
            nonlocal header
            if rec.kind == EPISODE:
                try:
                    ep = codec.own(codec.episode_from_wire(codec.unpack(rec.body)))
                except CodecError as e:
                    r.losses.append(f"snapshot-{r.base:08d}.bin offset {rec.offset}: {e}")
                    return
                state.episodes[ep.key] = ep
            elif rec.kind == HEADER and header is None:
                header = rec.meta

        sc = records.scan_file(path, keep=False, visit=load)
        r.formats.add(sc.format)
        state.load_header(header)
        state.rebuild_refs()

    def _replay_log(self, gen: int, state: BufferState, r: _Restore) -> Scan:
        name = f"log-{gen:08d}.bin"
        episodes, flagged = 0, 0

        def replay(rec: records.Record) -> None:
            nonlocal episodes, flagged
            if rec.kind == FILE and isinstance(rec.meta, dict) and rec.meta.get("commit"):
                flagged = 1
            try:
                episodes += self._apply(rec, state)
            except (CodecError, EpisodeError, KeyError, TypeError, ValueError) as e:
                r.losses.append(f"{name}: record at offset {rec.offset} is unreadable: {e}")
                r.damaged_logs.append(gen)

        sc = records.scan_file(self.path("log", gen), keep=False, visit=replay)
        if sc.damaged:
            r.losses.append(f"{name}: damaged records: {describe(sc)}")
            r.damaged_logs.append(gen)
        r.found[gen] = (sc.intact_end, episodes, flagged)
        self.records_since_snapshot = sc.count
        return sc

    @staticmethod
    def _apply(rec: records.Record, state: BufferState) -> int:
        """Apply one log record to `state`; returns the episodes an insert record carries."""
        if rec.kind == INSERT:
            wires = codec.unpack(rec.body)["episodes"]
            eps = [codec.own(codec.episode_from_wire(w)) for w in wires]
            for ep in eps:  # all or nothing, as when it was inserted
                if state.schema is not None:
                    ep.validate(state.schema)
            for ep in eps:
                state.insert(ep, [t for t in rec.meta["tables"] if isinstance(t, str)])
            return len(eps)
        if rec.kind == SAMPLE:
            if rec.meta["table"] in state.tables:
                state.apply_sample(rec.meta["table"], [tuple(k) for k in rec.meta["keys"]])
        elif rec.kind == SCHEMA:
            state.schema = EpisodeSchema.from_dict(rec.meta)
        elif rec.kind == FILE and state.schema is None and rec.meta.get("schema"):
            state.schema = EpisodeSchema.from_dict(rec.meta["schema"])
        return 0

    def _open_after_restore(self, state: BufferState, r: _Restore) -> None:
        """Open the log to append to; after a fallback, a repair or format-1 files, write a
        fresh snapshot first; remove generations no longer needed; write the marks."""
        self.gen, self.base = r.top, r.base
        self.commit.open(self._fsync_dir)
        if r.losses or r.bad_snaps or 1 in r.formats:
            for s in r.bad_snaps:
                self._set_aside(self.path("snapshot", s))
            for g in set(r.damaged_logs):
                self._set_aside(self.path("log", g))
            self.snapshot(state)  # log top+1 and snapshot top+1
            if r.losses:  # nothing older is restorable as it was: keep only the new one
                self._retain({self.base}, self.base)
            self.write_marks(sync=True, tail=self._tail)
            return
        if r.torn is not None:
            with open(self.path("log", r.top), "r+b") as f:
                f.truncate(r.torn.intact_end)
                os.fsync(f.fileno())
        self.marks = {g: found[:2] for g, found in r.found.items() if g != r.top}
        fd = self._open_log(r.top, state.schema, r.found.get(r.top, (0, 0))[1])
        os.fsync(fd)  # what a crash left written but unsynced is durable before it counts
        # The fallback to keep: the previous snapshot, or the empty state if log-0 is there.
        from_zero = all(g in r.logs for g in range(0, r.base))
        prev = max((s for s in r.snaps if s < r.base), default=0 if from_zero else r.base)
        self._retain({r.base, prev}, prev)
        self.write_marks(sync=True, tail=self._tail)

    def _set_aside(self, path: str) -> None:
        if os.path.exists(path):
            os.replace(path, path + ".damaged")
            log.error("%s set aside as %s.damaged", path, os.path.basename(path))

    def _remove_temp_files(self) -> None:
        for name in os.listdir(self.dir):
            if TEMP.match(name):
                os.remove(os.path.join(self.dir, name))
                log.info("removed %s, left by an interrupted snapshot", name)
