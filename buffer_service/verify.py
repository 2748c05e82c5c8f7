"""`credit buffer verify DIR`: what a snapshot folder holds, checked without changing it.

Every file is read record by record (checksums, damaged stretches with their offsets, torn
tails), then the folder is restored in memory exactly as `credit buffer serve` would, into
the tables recorded in its files (format 2) or the ones given (format 1 files record none).
"""

from __future__ import annotations

import contextlib
import os
from typing import Any

from buffer_service import codec, records
from buffer_service.config import BufferConfig, TableConfig, default_tables
from buffer_service.records import EPISODE, FILE, INSERT, Scan
from buffer_service.snapshots import snapshot_problem
from buffer_service.state import BufferState
from buffer_service.storage import NAME, TEMP, Storage, StorageError


def _episodes(scan: Scan) -> int:
    n = 0
    for rec in scan.records:
        if rec.kind == EPISODE:
            n += 1
        elif rec.kind == INSERT:
            with contextlib.suppress(codec.CodecError, KeyError, TypeError):
                n += len(codec.unpack(rec.body)["episodes"])
    return n


def file_report(name: str, scan: Scan) -> dict[str, Any]:
    """One file: role, generation, format, size, records, episodes, damage."""
    m = NAME.match(name)
    assert m is not None
    out: dict[str, Any] = {
        "file": name,
        "role": m.group(1),
        "generation": int(m.group(2)),
        "format": scan.format,
        "bytes": scan.size,
        "records": len(scan.records),
        "episodes": _episodes(scan),
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
        scan = records.scan_file(os.path.join(directory, name))
        files.append(file_report(name, scan))
        if scan.records and scan.records[0].kind == FILE and scan.records[0].meta.get("tables"):
            recorded = scan.records[0].meta["tables"]  # sorted by name: the newest wins
    if recorded is not None:
        tables, source = tuple(TableConfig.from_dict(t) for t in recorded), "files"
    else:
        tables, source = tables or default_tables(), "arguments"
    out: dict[str, Any] = {"dir": directory, "files": files, "leftovers": leftovers}
    out["tables_from"] = source
    out["restore"] = _restore(directory, tables, repair=False)
    damaged = any(f["damaged"] for f in files)
    out["ok"] = bool(out["restore"]["ok"]) and not damaged
    if not out["restore"]["ok"]:
        out["restore_with_repair"] = _restore(directory, tables, repair=True)
    return out
