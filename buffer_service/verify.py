"""`credit buffer verify DIR`: what a snapshot folder holds, checked without changing it.

Every file is read record by record (checksums, damaged stretches with their offsets, torn
tails), then the folder is restored in memory exactly as `credit buffer serve` would, into
the tables recorded in its files (format 2) or the ones given (format 1 files record none),
which includes checking every log against its high-water mark in ``commit.bin`` (a log cut
short or missing is a loss, named with the acknowledged episodes missing).
"""

from __future__ import annotations

import contextlib
import os
from typing import Any

from buffer_service import codec, commit, records
from buffer_service.config import BufferConfig, TableConfig, default_tables
from buffer_service.records import EPISODE, FILE, INSERT, Scan
from buffer_service.snapshots import snapshot_problem
from buffer_service.state import BufferState
from buffer_service.storage import NAME, TEMP, Storage, StorageError


def _episodes(rec: records.Record) -> int:
    if rec.kind == EPISODE:
        return 1
    if rec.kind == INSERT:
        with contextlib.suppress(codec.CodecError, KeyError, TypeError):
            return len(codec.unpack(rec.body)["episodes"])
    return 0


def scan_counting(path: str) -> tuple[Scan, int, Any]:
    """(scan, episodes held, the FILE record's meta) of one file, read in bounded chunks."""
    episodes, first = 0, None

    def count(rec: records.Record) -> None:
        nonlocal episodes, first
        episodes += _episodes(rec)
        if first is None and rec.kind == FILE:
            first = rec.meta

    return records.scan_file(path, keep=False, visit=count), episodes, first


def file_report(name: str, scan: Scan, episodes: int) -> dict[str, Any]:
    """One file: role, generation, format, size, records, episodes, damage."""
    m = NAME.match(name)
    assert m is not None
    out: dict[str, Any] = {
        "file": name,
        "role": m.group(1),
        "generation": int(m.group(2)),
        "format": scan.format,
        "bytes": scan.size,
        "records": scan.count,
        "episodes": episodes,
        "damaged": [{"offset": o, "bytes": n, "reason": why} for o, n, why in scan.damaged],
        "torn_tail": {"offset": scan.torn[0], "bytes": scan.torn[1]} if scan.torn else None,
    }
    if out["role"] == "snapshot":
        out["problem"] = snapshot_problem(scan)
    return out


def _restore(directory: str, tables: tuple[TableConfig, ...], repair: bool) -> dict[str, Any]:
    state = BufferState(BufferConfig(tables=tables))
    try:
        info = Storage(directory, repair=repair, read_only=True).restore(state)
    except StorageError as e:
        return {"ok": False, "error": str(e)}
    st = state.stats()
    out = {"ok": not info["losses"], "snapshot": info["snapshot"], "logs": info["logs"]}
    out |= {"warnings": info["warnings"], "losses": info["losses"]}
    out |= {"schema": st["schema"], "episodes": st["episodes_stored"], "tables": st["tables"]}
    return out


def _commit_report(directory: str) -> dict[str, Any] | None:
    """The high-water marks commit.bin records (None when there is none)."""
    try:
        marks = commit.CommitFile(directory).read()
    except commit.CommitFileError as e:
        return {"error": str(e)}
    if marks is None:
        return None
    return {
        f"log-{g:08d}.bin": {"acknowledged_bytes": b, "acknowledged_episodes": e}
        for g, (b, e) in sorted(marks.items())
    }


def verify(directory: str, tables: tuple[TableConfig, ...] | None = None) -> dict[str, Any]:
    """Check `directory` offline.

    Args:
        directory: a buffer service's snapshot_dir.
        tables: table configs to restore into when the files record none (format 1);
            default: those recorded, else `default_tables()`.

    Returns:
        ``{"dir", "ok", "files": [file_report], "leftovers", "tables_from", "restore",
        "restore_with_repair"?}``; ``ok`` is false when anything is damaged or missing
        (`credit buffer serve` would refuse to start without ``--repair``).
    """
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"no folder {directory}")
    files, leftovers, recorded = [], [], None
    for name in sorted(os.listdir(directory)):
        if not NAME.match(name):
            if TEMP.match(name) or name.endswith(".damaged"):
                leftovers.append(name)
            continue
        scan, episodes, first = scan_counting(os.path.join(directory, name))
        files.append(file_report(name, scan, episodes))
        if isinstance(first, dict) and first.get("tables"):
            recorded = first["tables"]  # sorted by name: the newest wins
    if recorded is not None:
        tables, source = tuple(TableConfig.from_dict(t) for t in recorded), "files"
    else:
        tables, source = tables or default_tables(), "arguments"
    out: dict[str, Any] = {"dir": directory, "files": files, "leftovers": leftovers}
    out["commit"] = _commit_report(directory)
    out["tables_from"] = source
    out["restore"] = _restore(directory, tables, repair=False)
    damaged = any(f["damaged"] for f in files)
    out["ok"] = bool(out["restore"]["ok"]) and not damaged
    if not out["restore"]["ok"]:
        out["restore_with_repair"] = _restore(directory, tables, repair=True)
    return out
