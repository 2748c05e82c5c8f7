"""Acknowledged data that disappears is detected (issue 40): a log cut short (at a record
boundary or inside a record) or deleted is refused at restart and by verify, naming the
file and the acknowledged episodes missing, unless told to accept the loss; a crash's torn
tail after the mark stays accepted. Also: restore reads logs in bounded chunks, and the log
is compacted by bytes too."""

from __future__ import annotations

import os
import time
import tracemalloc

import pytest

from buffer_service import codec, records
from buffer_service.config import BufferConfig
from buffer_service.episode import EpisodeSchema
from buffer_service.state import BufferState
from buffer_service.storage import Storage, StorageError
from buffer_service.verify import verify
from tests.buffer_service.conftest import make_episode, table
from tests.buffer_service.test_recovery import boot, held

LOG0 = "log-00000000.bin"


def ten_inserts(path, **kw) -> list[records.Record]:
    srv, c = boot(path, **kw)
    try:
        for i in range(10):
            c.insert([make_episode(0, i)])
    finally:
        c.close()
        srv.stop(snapshot=False)
    return [r for r in records.scan_file(str(path / LOG0)).records if r.kind == records.INSERT]


def cut(path, size: int) -> None:
    with open(path, "r+b") as f:
        f.truncate(size)


@pytest.mark.parametrize("where", ["boundary", "mid-record"])
def test_a_log_cut_short_is_refused_naming_the_file_and_the_missing_episodes(tmp_path, where):
    inserts = ten_inserts(tmp_path)
    cut(tmp_path / LOG0, inserts[3].offset + (0 if where == "boundary" else 30))
    want = rf"{LOG0} ends at byte {inserts[3].offset}.*7 of 10 acknowledged episodes"
    with pytest.raises(StorageError, match=want):
        boot(tmp_path)
    report = verify(str(tmp_path))
    assert not report["ok"] and "7 of 10 acknowledged episodes" in report["restore"]["error"]
    assert report["commit"][LOG0]["acknowledged_episodes"] == 10
    assert report["restore_with_repair"]["episodes"] == 3
    assert held(tmp_path, repair=True) == {(0, i) for i in range(3)}  # told to accept it
    assert held(tmp_path) == {(0, i) for i in range(3)}  # and then it is the new normal


def test_a_deleted_log_is_refused_beside_its_snapshot_and_alone(tmp_path):
    srv, c = boot(tmp_path)
    try:
        for i in range(10):
            c.insert([make_episode(0, i)])
            if i == 4:
                c.snapshot()
    finally:
        c.close()
        srv.stop(snapshot=False)
    os.remove(tmp_path / "log-00000001.bin")  # the active log, beside snapshot-1
    with pytest.raises(StorageError, match=r"log-00000001.bin is missing \(5 acknowledged"):
        boot(tmp_path)
    assert "log-00000001.bin is missing" in verify(str(tmp_path))["restore"]["error"]
    alone = tmp_path / "alone"
    ten_inserts(alone)
    os.remove(alone / LOG0)
    with pytest.raises(StorageError, match=rf"{LOG0} is missing \(10 acknowledged"):
        boot(alone)


def test_with_fsync_off_every_acknowledged_insert_is_marked(tmp_path):
    inserts = ten_inserts(tmp_path, fsync=False)
    cut(tmp_path / LOG0, inserts[-1].offset)
    with pytest.raises(StorageError, match="1 of 10 acknowledged episodes"):
        boot(tmp_path)


def test_a_damaged_commit_slot_falls_back_to_the_other_and_two_are_refused(tmp_path):
    from buffer_service import commit

    ten_inserts(tmp_path)
    path = tmp_path / commit.NAME
    f = commit.CommitFile(str(tmp_path))
    f.read()
    newest = (f.seq % 2) * commit.SLOT
    data = bytearray(path.read_bytes())
    data[newest + commit.HEAD.size + 2] ^= 0xFF
    path.write_bytes(bytes(data))
    assert len(held(tmp_path)) == 10  # the older slot's marks: a weaker check, no loss
    data = bytearray(path.read_bytes())
    for slot in (0, commit.SLOT):
        data[slot + commit.HEAD.size + 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(StorageError, match=r"commit\.bin: neither slot is intact"):
        boot(tmp_path)


def test_a_missing_commit_file_is_refused_when_the_logs_were_written_with_one(tmp_path):
    ten_inserts(tmp_path)
    os.remove(tmp_path / "commit.bin")
    with pytest.raises(StorageError, match=r"commit\.bin is missing"):
        boot(tmp_path)


MID = EpisodeSchema(n_agents=4, obs_dim=64, state_dim=64, n_actions=4, max_t=60)  # ~80 KB


def test_restore_reads_a_log_in_bounded_chunks(tmp_path):
    cfg = BufferConfig(tables=(table("cycling", "cycling", capacity=2, k=1),), schema=MID)
    storage = Storage(str(tmp_path))
    storage.restore(BufferState(cfg))
    for i in range(200):  # ~16 MB of log; the table keeps only the newest two episodes
        msg = {"op": "insert", "v": 1, "episodes": [make_episode(0, i, t=60, schema=MID)]}
        msg["episodes"] = [codec.episode_to_wire(ep) for ep in msg["episodes"]]
        storage.append_insert(["cycling"], codec.pack(msg))
    storage.close()
    assert os.path.getsize(tmp_path / LOG0) > 15 << 20
    state = BufferState(cfg)
    tracemalloc.start()
    try:
        Storage(str(tmp_path), read_only=True).restore(state)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(state.episodes) == 2
    assert peak < 4 << 20, peak  # about one record and a few episodes, not the log


def test_the_log_is_compacted_by_bytes_too(tmp_path):
    srv, c = boot(tmp_path, schema=MID, snapshot_every_inserts=0, snapshot_every_bytes=1 << 20)
    try:
        for i in range(20):  # ~1.6 MB of log
            c.insert([make_episode(0, i, t=60, schema=MID)])
        deadline = time.monotonic() + 10
        while c.stats()["generation"] < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        st = c.stats()
        assert st["generation"] >= 1 and st["log_bytes"] < 1 << 20
    finally:
        c.close()
        srv.stop(snapshot=False)
