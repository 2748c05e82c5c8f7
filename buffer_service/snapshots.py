"""Snapshots of the buffer service's durable folder: writing one (`SnapshotJob`, started by
`storage.Storage.begin_snapshot`) and checking a scanned one (`snapshot_problem`)."""

from __future__ import annotations

import logging
import os
from typing import TYPE_CHECKING

from buffer_service import codec, records
from buffer_service.records import END, EPISODE, FILE, HEADER, Scan
from buffer_service.state import StateCopy

if TYPE_CHECKING:  # storage imports this module; the type is only named here
    from buffer_service.storage import Storage

log = logging.getLogger(__name__)

FILE_MODE = 0o644
SYNC_EVERY = 4 << 20  # snapshot bytes written between fdatasyncs


def snapshot_problem(scan: Scan) -> str | None:
    """Why a scanned snapshot cannot be used as it is (None: it is intact and complete)."""
    if scan.damaged:
        return "is damaged: " + describe(scan)
    if scan.torn:
        return f"is cut short at offset {scan.torn[0]}"
    last = scan.last
    if last is None or HEADER not in scan.head_kinds or last.kind != END:
        return "incomplete (no header or no end record)"
    if scan.format == 2:
        held = scan.kinds.get(EPISODE, 0)
        if scan.head_kinds[0] != FILE or last.meta.get("episodes") != held:
            return f"is incomplete ({held} episode records, the end record disagrees)"
    return None


def describe(scan: Scan) -> str:
    return "; ".join(f"{size} bytes at offset {off} ({why})" for off, size, why in scan.damaged)


class SnapshotJob:
    """Writes one snapshot from a `StateCopy`; see `Storage.begin_snapshot`."""

    def __init__(self, storage: Storage, gen: int, copy: StateCopy) -> None:
        self.storage, self.gen, self.copy = storage, gen, copy

    def write(self) -> str:
        st = self.storage
        final = st.path("snapshot", self.gen)
        tmp = final + ".tmp"
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
        try:
            records.write(fd, FILE, st._file_meta("snapshot", self.gen, self.copy.schema))
            records.write(fd, HEADER, self.copy.header())
            unsynced = 0
            for ep in self.copy.episodes:
                unsynced += records.write(fd, EPISODE, None, codec.pack(codec.episode_to_wire(ep)))
                if unsynced >= SYNC_EVERY:  # little dirty data at a time: the log's fsyncs
                    os.fdatasync(fd)  # and writes do not queue behind the whole snapshot
                    unsynced = 0
            records.write(fd, END, {"episodes": len(self.copy.episodes)})
            os.fsync(fd)
        except BaseException:
            os.close(fd)
            os.remove(tmp)
            raise
        os.close(fd)
        os.replace(tmp, final)
        st._fsync_dir()
        previous, st.base = st.base, self.gen
        st._retain({self.gen, previous}, previous)  # the previous one stays as a fallback
        if st.commit.fd is not None:
            st.sync_retired()
            st.write_marks(sync=True)  # without the marks of the logs just removed
        log.info("snapshot %s: %d episodes", final, len(self.copy.episodes))
        return final
