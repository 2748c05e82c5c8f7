"""A full disk refuses instead of corrupting (issue 40): an insert that cannot be logged is
rolled back and refused with ``storage_full``, samples go on, shutdown and restart say so
without a traceback, and once space returns everything acknowledged is there with nothing
to repair. The disk fills by an injected write failure here (a real tmpfs: test_chaos)."""

from __future__ import annotations

import errno
import os

import pytest

from buffer_service.client import BufferServiceError
from buffer_service.verify import verify
from tests.buffer_service.conftest import make_episode
from tests.buffer_service.test_recovery import boot, held

LOG0 = "log-00000000.bin"


class FullDisk:
    """Writes to files under `folder` fail as on a full disk while `full`: a writev
    writes half of its bytes, any further write raises ENOSPC."""

    def __init__(self, folder, monkeypatch) -> None:
        self.folder, self.full = str(folder), False
        real_writev, real_write = os.writev, os.write

        def ours(fd: int) -> bool:
            try:
                return os.readlink(f"/proc/self/fd/{fd}").startswith(self.folder)
            except OSError:
                return False

        def writev(fd, buffers):
            if not (self.full and ours(fd)):
                return real_writev(fd, buffers)
            data = b"".join(bytes(b) for b in buffers)
            return real_write(fd, data[: len(data) // 2])

        def write(fd, data):
            if self.full and ours(fd):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return real_write(fd, data)

        monkeypatch.setattr(os, "writev", writev)
        monkeypatch.setattr(os, "write", write)


def test_a_full_disk_refuses_inserts_by_name_and_loses_nothing(tmp_path, monkeypatch):
    disk = FullDisk(tmp_path, monkeypatch)
    srv, c = boot(tmp_path)
    try:
        for i in range(5):
            c.insert([make_episode(0, i)])
        size = os.path.getsize(tmp_path / LOG0)
        disk.full = True
        for i in range(5, 8):
            with pytest.raises(BufferServiceError, match="storage_full") as e:
                c.insert([make_episode(0, i)])
            assert e.value.code == "storage_full"
        assert os.path.getsize(tmp_path / LOG0) == size  # every failed append rolled back
        assert c.sample("replay", 3).batch_size == 3  # samples go on (their record skipped)
        st = c.stats()
        assert st["episodes_stored"] == 5 and st["unlogged_samples"] == 1
        disk.full = False  # space returns
        for i in range(5, 8):
            assert c.insert([make_episode(0, i)])["inserted"] == 1
    finally:
        c.close()
        srv.stop(snapshot=False)
    report = verify(str(tmp_path))
    assert report["ok"], report  # nothing to repair
    assert held(tmp_path) == {(0, i) for i in range(8)}


def test_shutdown_and_restart_on_a_full_disk_say_so(tmp_path, monkeypatch):
    from buffer_service.storage import WriteError

    disk = FullDisk(tmp_path, monkeypatch)
    srv, c = boot(tmp_path)
    c.insert([make_episode(0, 0)])
    c.close()
    disk.full = True
    srv.stop()  # the final snapshot cannot be written: named, no exception, nothing lost
    assert srv.server.close_error.startswith("storage_full")
    assert sorted(os.listdir(tmp_path)) == ["commit.bin", LOG0]  # no partial files left
    assert held(tmp_path) == {(0, 0)}  # a restart that needs no write works while full
    with pytest.raises(WriteError, match="No space left") as e:  # one that must write
        boot(tmp_path / "fresh")
    assert e.value.code == "storage_full"
    disk.full = False
    assert held(tmp_path) == {(0, 0)} and verify(str(tmp_path))["ok"]


def test_credit_buffer_serve_on_a_full_disk_exits_by_name(tmp_path, monkeypatch, caplog):
    import argparse

    from cluster.commands.buffer import cmd_serve, register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["buffer", "serve", "--snapshot-dir", str(tmp_path / "fresh")])
    FullDisk(tmp_path, monkeypatch).full = True
    assert cmd_serve(args) == 2
    assert "cannot start: storage_full" in caplog.text and "Traceback" not in caplog.text


def test_a_failed_fsync_is_not_acknowledged_and_writes_stop_until_restart(tmp_path, monkeypatch):
    srv, c = boot(tmp_path)
    try:
        c.insert([make_episode(0, 0)])
        real_fsync = os.fsync

        def fsync(fd):
            if os.readlink(f"/proc/self/fd/{fd}").startswith(str(tmp_path)):
                raise OSError(errno.EIO, os.strerror(errno.EIO))
            return real_fsync(fd)

        monkeypatch.setattr(os, "fsync", fsync)
        with pytest.raises(BufferServiceError, match="fsync failed"):
            c.insert([make_episode(0, 1)])  # written, never acknowledged
        monkeypatch.setattr(os, "fsync", real_fsync)
        with pytest.raises(BufferServiceError, match="restart the service"):
            c.insert([make_episode(0, 2)])  # the kernel may have dropped the pages
        assert c.sample("replay", 1).batch_size == 1  # reads go on
    finally:
        c.close()
        srv.stop(snapshot=False)
    assert {(0, 0)} <= held(tmp_path) <= {(0, 0), (0, 1)}
