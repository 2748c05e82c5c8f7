"""Log + snapshot durability: restore, torn tails, compaction, and a real kill -9."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from buffer_service import codec, records
from buffer_service.client import BufferClient
from buffer_service.config import BufferConfig
from buffer_service.runner import start_server_thread
from buffer_service.state import BufferState
from buffer_service.storage import StorageError
from tests.buffer_service.conftest import SCHEMA, make_episode, table

REPO = Path(__file__).resolve().parents[2]
TABLES = (table("cycling", "cycling", capacity=100, k=2), table("replay", "replay", capacity=100))


def boot(path, **kw):
    kw.setdefault("tables", TABLES)
    kw.setdefault("schema", SCHEMA)
    srv = start_server_thread(BufferConfig(snapshot_dir=str(path), **kw))
    return srv, BufferClient(port=srv.port, max_retries=2)


def test_restore_from_log_without_snapshot(tmp_path):
    srv, c = boot(tmp_path, snapshot_every_inserts=0)
    c.insert([make_episode(0, i) for i in range(5)])
    c.insert([make_episode(1, 0)], tables=["replay"])
    c.sample("cycling", 5)  # every cycling item sampled once (K = 2)
    c.close()
    srv.stop(snapshot=False)  # like a crash: only the log holds the state
    assert sorted(os.listdir(tmp_path)) == ["commit.bin", "log-00000000.bin"]
    srv, c = boot(tmp_path, snapshot_every_inserts=0)
    try:
        st = c.stats()
        assert st["episodes_stored"] == 6
        assert st["tables"]["cycling"]["size"] == 5 and st["tables"]["replay"]["size"] == 6
        assert c.insert([make_episode(0, 3)]) == {"inserted": 0, "duplicates": 1}
        c.sample("cycling", 5)  # the second sample after restart retires them all
        assert c.stats()["tables"]["cycling"]["size"] == 0
    finally:
        c.close()
        srv.stop(snapshot=False)


def test_torn_last_record_is_dropped(tmp_path):
    srv, c = boot(tmp_path, snapshot_every_inserts=0)
    c.insert([make_episode(0, 0)])
    c.close()
    srv.stop(snapshot=False)
    log_path = tmp_path / "log-00000000.bin"
    msg = {"op": "insert", "v": 1, "episodes": [codec.episode_to_wire(make_episode(0, 1))]}
    record = b"".join(records.encode(records.INSERT, {"tables": ["cycling"]}, codec.pack(msg)))
    with open(log_path, "ab") as f:  # a crash mid-append (never acknowledged): half a record
        f.write(record[: len(record) // 2])
    srv, c = boot(tmp_path, snapshot_every_inserts=0)
    try:
        assert c.stats()["episodes_stored"] == 1
        assert c.insert([make_episode(0, 1)])["inserted"] == 1  # it was never acked
    finally:
        c.close()
        srv.stop(snapshot=False)
    size = log_path.stat().st_size
    with open(log_path, "ab") as f:  # garbage after the records: not what a crash leaves
        f.write(b"\x01" * 300)
    with pytest.raises(StorageError, match=rf"log-00000000.bin.*300 bytes at offset {size}"):
        boot(tmp_path, snapshot_every_inserts=0)
    srv, c = boot(tmp_path, snapshot_every_inserts=0, repair=True)
    try:
        assert c.stats()["episodes_stored"] == 2
    finally:
        c.close()
        srv.stop(snapshot=False)
    assert (tmp_path / "log-00000000.bin.damaged").exists()  # kept for inspection


def test_snapshot_compacts_the_log(tmp_path):
    srv, c = boot(tmp_path, snapshot_every_inserts=3)
    for i in range(7):
        c.insert([make_episode(4, i)])
    c.sample("cycling", 7)
    path = c.snapshot()  # after those in progress (each insert's snapshot runs in a thread)
    g = int(Path(path).name[len("snapshot-") : -len(".bin")])
    assert g >= 2  # at least one snapshot was due before (they may coalesce)
    assert c.stats()["generation"] == g
    # the previous snapshot and its log stay as the fallback; older ones are gone
    names = [f"log-{g - 1:08d}.bin", f"log-{g:08d}.bin"]
    names += [f"snapshot-{g - 1:08d}.bin", f"snapshot-{g:08d}.bin", "commit.bin"]
    assert sorted(os.listdir(tmp_path)) == sorted(names)
    c.insert([make_episode(4, 7)])
    c.close()
    srv.stop(snapshot=False)
    srv, c = boot(tmp_path)
    try:
        st = c.stats()
        assert st["episodes_stored"] == 8 and st["tables"]["cycling"]["size"] == 8
        c.sample("cycling", 8)  # the seven sampled before the snapshot now reach K = 2
        assert seqs_left(c) == [7]
    finally:
        c.close()
        srv.stop()


def seqs_left(c: BufferClient) -> list[int]:
    n = c.stats()["tables"]["cycling"]["size"]
    return sorted(int(s) for s in c.sample("cycling", n).episode_seq)


def _serve_cli(snap: Path, port: int, port_file: Path, capacity: int = 1000) -> subprocess.Popen:
    if port_file.exists():
        port_file.unlink()
    cmd = [
        sys.executable, "-m", "cluster.cli", "buffer", "serve", "--port", str(port),
        "--port-file", str(port_file), "--snapshot-dir", str(snap), "--snapshot-every", "7",
        "--table", f"name=all,kind=cycling,capacity={capacity},max_times_sampled=1",
    ]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 30
    while not port_file.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError(f"buffer serve did not start: {proc.stderr.read().decode()}")
        time.sleep(0.05)
    return proc


def _stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        proc.kill()


def test_kill_9_loses_no_acked_episode(tmp_path):
    snap, port_file = tmp_path / "snap", tmp_path / "port.json"
    proc = _serve_cli(snap, 0, port_file)
    port = json.loads(port_file.read_text())["port"]
    client = BufferClient(port=port, schema=SCHEMA, backoff_s=0.05, max_retries=40)
    acked: list[tuple[int, int]] = []
    killed = threading.Event()
    errors: list[BaseException] = []

    def actor():
        try:
            for seq in range(60):  # bounded; keeps inserting through the kill
                client.insert([make_episode(7, seq, t=3)])
                acked.append((7, seq))
                if seq == 40:
                    killed.wait(30)
        except BaseException as e:  # surfaced below
            errors.append(e)

    th = threading.Thread(target=actor)
    th.start()
    try:
        while len(acked) < 25 and th.is_alive():
            time.sleep(0.01)
        os.kill(proc.pid, signal.SIGKILL)  # mid-stream: a request may be in flight
        proc.wait(10)
        n_before = len(acked)
        proc = _serve_cli(snap, port, port_file)  # same port: the client reconnects itself
        killed.set()
        th.join(60)
        assert not errors, errors
        assert len(acked) == 60 and n_before >= 25
        st = client.stats()
        assert st["episodes_stored"] == 60 and st["tables"]["all"]["size"] == 60
        batch = client.sample("all", 60)
        keys = list(zip(batch.actor_id.tolist(), batch.episode_seq.tolist(), strict=True))
        assert sorted(keys) == sorted(acked) and len(set(keys)) == 60  # exactly once each
        assert client.reconnects >= 2
    finally:
        killed.set()
        client.close()
        _stop(proc)


def test_one_fsync_acknowledges_every_record_written_before_it(tmp_path):
    import asyncio

    from buffer_service.server import GroupCommit
    from buffer_service.storage import Storage

    storage = Storage(str(tmp_path))
    storage.restore(BufferState(BufferConfig(tables=TABLES)))
    commits = GroupCommit(storage)
    records = [storage.append_insert(["replay"], b"x") for _ in range(3)]

    async def three_inserts_waiting_together():
        await asyncio.gather(*(commits.durable(r) for r in records))
        await commits.durable(records[-1])  # already durable: no second fsync

    asyncio.run(three_inserts_waiting_together())
    assert (commits.synced, commits.fsyncs) == (3, 1)
    storage.append_insert(["replay"], b"y")
    asyncio.run(commits.durable(4))
    assert (commits.synced, commits.fsyncs) == (4, 2)
    storage.append_insert(["replay"], b"z")
    asyncio.run(commits.durable(5, alone=True))  # one connection: fsync inline, same count
    assert (commits.synced, commits.fsyncs) == (5, 3)
    storage.snapshot(BufferState(BufferConfig(tables=TABLES)))
    storage.close()


def test_kill_9_with_concurrent_clients_loses_no_acked_episode(tmp_path):
    """Four clients insert at once, so their inserts share fsyncs (group commit); a kill -9
    mid-stream must still lose none that was acknowledged."""
    snap, port_file = tmp_path / "snap", tmp_path / "port.json"
    proc = _serve_cli(snap, 0, port_file)
    port = json.loads(port_file.read_text())["port"]
    acked: list[tuple[int, int]] = []
    errors: list[BaseException] = []
    clients = [
        BufferClient(port=port, schema=SCHEMA, backoff_s=0.05, max_retries=40) for _ in range(4)
    ]

    def actor(i: int):
        try:
            for seq in range(40):
                clients[i].insert([make_episode(i, seq, t=3)])
                acked.append((i, seq))
        except BaseException as e:  # surfaced below
            errors.append(e)

    threads = [threading.Thread(target=actor, args=(i,)) for i in range(4)]
    for th in threads:
        th.start()
    try:
        while len(acked) < 40 and any(th.is_alive() for th in threads):
            time.sleep(0.005)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        proc = _serve_cli(snap, port, port_file)
        for th in threads:
            th.join(60)
        assert not errors, errors
        assert len(acked) == 160
        st = clients[0].stats()
        assert st["episodes_stored"] == 160
        batch = clients[0].sample("all", 160)
        keys = list(zip(batch.actor_id.tolist(), batch.episode_seq.tolist(), strict=True))
        assert sorted(keys) == sorted(acked)  # every acknowledged episode, exactly once
    finally:
        for c in clients:
            c.close()
        _stop(proc)
