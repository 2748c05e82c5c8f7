"""Snapshots of the buffer service's durable folder: writing one's file (`write_file`, for
`storage.SnapshotJob`) and checking a scanned one (`snapshot_problem`)."""

from __future__ import annotations

import os

from buffer_service import codec, records
from buffer_service.records import END, EPISODE, FILE, HEADER, Scan
from buffer_service.state import StateCopy

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


def write_file(final: str, file_meta: dict, copy: StateCopy) -> None:
    """Write the snapshot of `copy` to `final`: into ``final + ".tmp"``, fsynced, then
    renamed over `final` (the folder's fsync is the caller's)."""
    tmp = final + ".tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, FILE_MODE)
    try:
        records.write(fd, FILE, file_meta)
        records.write(fd, HEADER, copy.header())
        unsynced = 0
        for ep in copy.episodes:
            unsynced += records.write(fd, EPISODE, None, codec.pack(codec.episode_to_wire(ep)))
            if unsynced >= SYNC_EVERY:  # little dirty data at a time: the log's fsyncs
                os.fdatasync(fd)  # and writes do not queue behind the whole snapshot
                unsynced = 0
        records.write(fd, END, {"episodes": len(copy.episodes)})
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        os.remove(tmp)
        raise
    os.close(fd)
    os.replace(tmp, final)
