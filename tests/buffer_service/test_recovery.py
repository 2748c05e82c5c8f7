"""Damaged files are detected, named and worked around, never silently dropped (issue 14);
snapshots run beside requests and leave nothing behind a crash at any point."""

from __future__ import annotations

import json
import os
import shutil
import struct
import threading
import zlib

import msgpack
import pytest

from buffer_service import codec, records
from buffer_service.client import BufferClient
from buffer_service.config import BufferConfig
from buffer_service.runner import start_server_thread
from buffer_service.state import BufferState
from buffer_service.storage import NAME, SnapshotJob, Storage, StorageError
from buffer_service.verify import verify
from tests.buffer_service.conftest import SCHEMA, make_episode, table

TABLES = (table("cycling", "cycling", capacity=100, k=2), table("replay", "replay", capacity=100))
ALL = {(0, i) for i in range(15)}


def boot(path, **kw):
    kw.setdefault("tables", TABLES)
    kw.setdefault("schema", SCHEMA)
    kw.setdefault("snapshot_every_inserts", 0)
    srv = start_server_thread(BufferConfig(snapshot_dir=str(path), **kw))
    return srv, BufferClient(port=srv.port, max_retries=2)


def held(path, **kw) -> set[tuple[int, int]]:
    """The episodes a server started on `path` holds (then stopped without a snapshot)."""
    srv, c = boot(path, **kw)
    try:
        return set(srv.server.state.episodes)
    finally:
        c.close()
        srv.stop(snapshot=False)


def three_generations(path) -> None:
    """Episodes 0-4, snapshot, 5-9, snapshot, 10-14, each one insert; no final snapshot.
    Leaves snapshot-1, snapshot-2 (the previous one is kept as a fallback), log-1, log-2."""
    srv, c = boot(path)
    try:
        for i in range(15):
            c.insert([make_episode(0, i)])
            if i in (4, 9):
                c.snapshot()
    finally:
        c.close()
        srv.stop(snapshot=False)
    names = ["commit.bin", "log-00000001.bin", "log-00000002.bin", "snapshot-00000001.bin"]
    assert sorted(os.listdir(path)) == [*names, "snapshot-00000002.bin"]


def flip(path, offset: int) -> None:
    with open(path, "r+b") as f:
        f.seek(offset)
        b = f.read(1)
        f.seek(offset)
        f.write(bytes([b[0] ^ 0x40]))


def inserts(path) -> list[records.Record]:
    return [r for r in records.scan_file(str(path)).records if r.kind == records.INSERT]


@pytest.mark.parametrize("where", ["payload", "header"])
def test_a_damaged_log_record_is_named_and_the_records_after_it_recovered(tmp_path, where):
    three_generations(tmp_path)
    log2 = tmp_path / "log-00000002.bin"
    victim = inserts(log2)[2]  # episode 12 of 10-14
    flip(log2, victim.offset + (records.HEAD_SIZE + 40 if where == "payload" else 9))
    with pytest.raises(StorageError, match=rf"log-00000002.bin.* at offset {victim.offset}"):
        boot(tmp_path)
    report = verify(str(tmp_path))
    assert report["ok"] is False and report["restore"]["ok"] is False
    (log_report,) = [f for f in report["files"] if f["file"] == "log-00000002.bin"]
    assert [d["offset"] for d in log_report["damaged"]] == [victim.offset]
    assert log_report["episodes"] == 4  # the other inserts of the log
    assert report["restore_with_repair"]["episodes"] == 14
    assert held(tmp_path, repair=True) == ALL - {(0, 12)}  # 13 and 14 are still there
    assert (tmp_path / "log-00000002.bin.damaged").exists()
    assert held(tmp_path) == ALL - {(0, 12)}  # repaired: starts without --repair now


def test_a_damaged_snapshot_falls_back_to_the_previous_one_and_the_logs(tmp_path, caplog):
    three_generations(tmp_path)
    snap2 = tmp_path / "snapshot-00000002.bin"
    episode = [r for r in records.scan_file(str(snap2)).records if r.kind == records.EPISODE][3]
    flip(snap2, episode.offset + records.HEAD_SIZE + 100)
    report = verify(str(tmp_path))
    assert report["ok"] is False  # damage is reported even though nothing is lost
    assert report["restore"]["ok"] is True and report["restore"]["episodes"] == 15
    assert report["restore"]["snapshot"] == 1 and report["restore"]["logs"] == [1, 2]
    assert held(tmp_path) == ALL
    assert "snapshot-00000002.bin is damaged" in caplog.text
    assert (tmp_path / "snapshot-00000002.bin.damaged").exists()
    assert held(tmp_path) == ALL  # from the fresh snapshot written at the fallback
    assert verify(str(tmp_path))["restore"]["snapshot"] == 3


def test_the_service_never_comes_up_silently_empty(tmp_path, caplog):
    from cluster.cli import main

    three_generations(tmp_path)
    for name in ("snapshot-00000001.bin", "snapshot-00000002.bin"):
        episode = [r for r in records.scan_file(str(tmp_path / name)).records][-2]
        flip(tmp_path / name, episode.offset + records.HEAD_SIZE + 50)
    argv = ["buffer", "serve", "--snapshot-dir", str(tmp_path), "--port", "0"]
    assert main(argv) == 2  # the real command refuses, naming the files
    assert "refusing to start" in caplog.text
    assert "snapshot-00000002.bin" in caplog.text and "snapshot-00000001.bin" in caplog.text
    got = held(tmp_path, repair=True)  # the newest snapshot's intact episodes + its log
    assert (0, 14) in got and len(got) == 14
    assert "--repair discards" in caplog.text


def test_the_launchers_buffer_process_refuses_damage_unless_told_to_repair(tmp_path):
    from cluster.launch.buffer_proc import BufferProcess

    data = tmp_path / "buffer" / "data"
    three_generations(data)
    for name in ("snapshot-00000001.bin", "snapshot-00000002.bin"):
        episode = [r for r in records.scan_file(str(data / name)).records][-2]
        flip(data / name, episode.offset + records.HEAD_SIZE + 50)
    proc = BufferProcess(TABLES, SCHEMA, tmp_path / "buffer", metrics=False)
    with pytest.raises(RuntimeError, match="refusing to start"):
        proc.start()
    proc = BufferProcess(TABLES, SCHEMA, tmp_path / "buffer", metrics=False, repair=True)
    proc.start()
    try:
        with BufferClient(port=proc.port, token=proc.token, max_retries=2) as c:
            assert c.stats()["episodes_stored"] == 14  # the newest snapshot's intact ones + its log
    finally:
        proc.stop()
    assert "--repair discards" in (tmp_path / "buffer" / "service.log").read_text()


def test_verify_command_prints_tables_episodes_and_damage(tmp_path, capsys):
    from cluster.cli import main

    three_generations(tmp_path)
    assert main(["buffer", "verify", str(tmp_path)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is True and report["tables_from"] == "files"
    assert report["restore"]["episodes"] == 15
    assert report["restore"]["tables"]["cycling"]["size"] == 15
    assert report["restore"]["tables"]["replay"]["capacity"] == 100
    assert {f["file"]: f["episodes"] for f in report["files"]} == {
        "log-00000001.bin": 5,
        "log-00000002.bin": 5,
        "snapshot-00000001.bin": 5,
        "snapshot-00000002.bin": 10,
    }
    victim = inserts(tmp_path / "log-00000001.bin")[1]
    flip(tmp_path / "log-00000001.bin", victim.offset + records.HEAD_SIZE + 10)
    assert main(["buffer", "verify", str(tmp_path)]) == 1
    report = json.loads(capsys.readouterr().out)
    damaged = {f["file"]: f["damaged"] for f in report["files"] if f["damaged"]}
    assert list(damaged) == ["log-00000001.bin"]
    assert damaged["log-00000001.bin"][0]["offset"] == victim.offset
    assert report["restore"]["ok"] is True  # log-1 is only the fallback's: nothing lost


def _legacy_record(kind: bytes, meta, body: bytes = b"") -> bytes:
    """A record as the buffer wrote it before issue 14 (format 1)."""
    m = msgpack.packb(meta, use_bin_type=True)
    crc = zlib.crc32(body, zlib.crc32(m))
    return struct.pack(">IIBI", len(m) + len(body), crc, kind[0], len(m)) + m + body


def test_format_1_folders_are_read_and_converted(tmp_path):
    log0 = [_legacy_record(records.SCHEMA, SCHEMA.to_dict())]
    for i in range(15):
        msg = {"op": "insert", "v": 1, "episodes": [codec.dense_to_wire(make_episode(0, i))]}
        log0.append(
            _legacy_record(records.INSERT, {"tables": ["cycling", "replay"]}, codec.pack(msg))
        )
    (tmp_path / "log-00000000.bin").write_bytes(b"".join(log0))
    assert held(tmp_path) == ALL
    formats = {f["file"]: f["format"] for f in verify(str(tmp_path))["files"]}
    assert formats == {"log-00000000.bin": 1, "log-00000001.bin": 2, "snapshot-00000001.bin": 2}
    assert held(tmp_path) == ALL


def test_files_are_created_0644_or_stricter(tmp_path):
    old = os.umask(0)
    try:
        srv, c = boot(tmp_path / "snap")
        c.insert([make_episode(0, 0)])
        c.snapshot()
        c.insert([make_episode(0, 1)])
        c.close()
        srv.stop()
    finally:
        os.umask(old)
    modes = {p.name: p.stat().st_mode & 0o777 for p in (tmp_path / "snap").iterdir()}
    assert modes and all(m & ~0o644 == 0 for m in modes.values()), modes


def test_inserts_and_samples_go_on_while_a_snapshot_is_written(tmp_path, monkeypatch):
    writing, finish = threading.Event(), threading.Event()
    real = SnapshotJob.write

    def held_up(self):
        writing.set()
        assert finish.wait(60)
        return real(self)

    monkeypatch.setattr(SnapshotJob, "write", held_up)
    srv, c = boot(tmp_path)
    other = BufferClient(port=srv.port, max_retries=0)
    paths: list[str] = []
    try:
        c.insert([make_episode(0, i) for i in range(5)])
        th = threading.Thread(target=lambda: paths.append(other.snapshot()))
        th.start()
        assert writing.wait(60)  # the snapshot file is being written now
        assert c.insert([make_episode(0, 5)])["inserted"] == 1
        assert c.sample("replay", 3).batch_size == 3
        assert c.stats()["episodes_stored"] == 6
        finish.set()
        th.join(60)
        assert paths and paths[0].endswith("snapshot-00000001.bin")
    finally:
        finish.set()
        other.close()
        c.close()
        srv.stop(snapshot=False)
    assert held(tmp_path) == {(0, i) for i in range(6)}  # the 6th is in the new log


KILLED, DONE = 9, 0
FILE_OPS = ("open", "write", "writev", "fsync", "replace", "remove")


def _snapshot_killed_at(path: str, kill_at: int) -> None:
    """In a forked child: a store with one snapshot behind it, then a snapshot that dies
    (os._exit: no cleanup, like kill -9) just before its `kill_at`-th file operation."""
    cfg = BufferConfig(tables=TABLES, schema=SCHEMA)
    storage, state = Storage(path), BufferState(cfg)
    storage.restore(state)
    for i in range(6):
        ep = make_episode(0, i)
        body = codec.pack({"op": "insert", "v": 1, "episodes": [codec.episode_to_wire(ep)]})
        storage.append_insert(["cycling", "replay"], body)
        state.insert(ep, ["cycling", "replay"])
        if i == 2:
            storage.snapshot(state)
    storage.sync()
    done = [0]

    def counted(fn):
        def op(*args, **kw):
            if done[0] == kill_at:
                os._exit(KILLED)
            done[0] += 1
            return fn(*args, **kw)

        return op

    for name in FILE_OPS:
        setattr(os, name, counted(getattr(os, name)))
    storage.snapshot(state)
    os._exit(DONE)


def test_a_crash_at_any_point_of_a_snapshot_loses_nothing_and_leaves_nothing(tmp_path):
    cfg = BufferConfig(tables=TABLES, schema=SCHEMA)
    for kill_at in range(200):
        path = str(tmp_path / f"kill-{kill_at}")
        pid = os.fork()
        if pid == 0:  # the child never returns into pytest
            try:
                _snapshot_killed_at(path, kill_at)
            finally:
                os._exit(99)
        code = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
        assert code in (KILLED, DONE), code
        storage, state = Storage(path), BufferState(cfg)
        storage.restore(state)
        storage.close()
        assert set(state.episodes) == {(0, i) for i in range(6)}, kill_at
        assert state.tables["cycling"].stats()["size"] == 6
        names = sorted(os.listdir(path))
        assert not [n for n in names if n.endswith(".tmp")], (kill_at, names)
        assert len([n for n in names if n.startswith("snapshot-")]) <= 2, (kill_at, names)
        assert "log-00000000.bin" not in names or "snapshot-00000002.bin" not in names
        if code == DONE:
            break
    assert kill_at >= 10, kill_at  # every file operation of a snapshot was a crash point


@pytest.mark.slow
def test_a_flipped_byte_anywhere_is_detected_and_never_loses_silently(tmp_path):
    """Flip one bit at every 7th byte of every file: the restore is then either complete
    (the byte was in a fallback, or the newest snapshot fell back) or refused; verify reports
    the damage every time."""
    base = tmp_path / "base"
    three_generations(base)
    cfg = BufferConfig(tables=TABLES, schema=SCHEMA)
    outcomes = {"complete": 0, "refused": 0}
    for name in sorted(n for n in os.listdir(base) if NAME.match(n)):  # (commit.bin: elsewhere)
        for offset in range(0, (base / name).stat().st_size, 7):
            work = tmp_path / f"{name}-{offset}"
            shutil.copytree(base, work)
            with open(work / name, "r+b") as f:
                f.seek(offset)
                byte = f.read(1)[0]
                f.seek(offset)
                f.write(bytes([byte ^ 0x01]))
            assert not verify(str(work))["ok"], (name, offset)
            state, storage = BufferState(cfg), Storage(str(work))
            try:
                storage.restore(state)
            except StorageError as e:
                assert name in str(e), (name, offset, str(e))
                outcomes["refused"] += 1
            else:
                storage.close()
                assert set(state.episodes) == ALL, (name, offset)
                outcomes["complete"] += 1
            shutil.rmtree(work)
    assert outcomes["refused"] and outcomes["complete"]
