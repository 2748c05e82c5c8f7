"""Chaos (issue 14): client processes insert while the service, a real `credit buffer serve`
subprocess on 127.0.0.1, is killed with kill -9 at random moments (snapshots included, as
one is due every 7 inserts); then every acknowledged episode must be held exactly once,
byte for byte. Issue 40 adds a full disk (a small tmpfs: inserts refused by name, samples
served, SIGTERM and a restart without a traceback, everything back once space returns)
and slow readers (the service's memory stays within its budget, others are served)."""

from __future__ import annotations

import contextlib
import json
import os
import random
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from buffer_service import codec
from buffer_service.client import BufferClient
from buffer_service.episode import EPISODE_ARRAYS, EPISODE_SCALARS
from buffer_service.verify import verify
from tests.buffer_service.conftest import SCHEMA, make_episode
from tests.buffer_service.test_durability import REPO, _serve_cli, _stop

CLIENTS, PER_CLIENT, KILLS = 4, 400, 12
CAPACITY = CLIENTS * PER_CLIENT


def _acked(path) -> tuple[list[int], list[str]]:
    lines = path.read_text().split() if path.exists() else []
    other = [x for x in lines if not x.isdigit() and x != "full"]
    return [int(x) for x in lines if x.isdigit()], other


@pytest.mark.slow
def test_kill_9_at_random_moments_loses_and_duplicates_no_acknowledged_episode(tmp_path):
    rng = random.Random(14)
    snap, port_file = tmp_path / "snap", tmp_path / "port.json"
    proc = _serve_cli(snap, 0, port_file, CAPACITY)
    port = json.loads(port_file.read_text())["port"]
    files = [tmp_path / f"acked-{i}.txt" for i in range(CLIENTS)]
    cmd = [sys.executable, "-m", "tests.buffer_service.chaos_client", str(port)]
    clients = [
        subprocess.Popen([*cmd, str(i), str(PER_CLIENT), str(files[i])], cwd=REPO)
        for i in range(CLIENTS)
    ]
    acked_at_kills = []  # episodes acknowledged when each kill was sent
    try:
        while sum(len(_acked(f)[0]) for f in files) < 50:  # the clients are under way
            time.sleep(0.05)
        for _ in range(KILLS):
            time.sleep(rng.uniform(0.05, 1.5))
            acked_at_kills.append(sum(len(_acked(f)[0]) for f in files))
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(10)
            proc = _serve_cli(snap, port, port_file, CAPACITY)  # same port: the clients reconnect
        for c in clients:
            assert c.wait(600) == 0
        for f in files:
            seqs, other = _acked(f)
            assert other == ["done"] and seqs == list(range(PER_CLIENT)), (f, other)
        # kills fell while the clients inserted (whether the last ones still did depends on
        # how long the restarts took against how fast the clients were)
        assert any(0 < n < CLIENTS * PER_CLIENT for n in acked_at_kills), acked_at_kills
        audit(port)
    finally:
        for c in clients:
            c.kill()
        _stop(proc)
    report = verify(str(snap))
    assert report["ok"] and not report["leftovers"], report


def audit(port: int, clients: int = CLIENTS, per_client: int = PER_CLIENT, seen=None) -> None:
    """Drain the K=1 cycling table: each episode comes out once (`seen`: those sampled
    before); compare every byte."""
    client = BufferClient(port=port, schema=SCHEMA)
    st = client.stats()
    seen = set(seen or ())
    assert st["episodes_stored"] + len(seen) == clients * per_client
    while (left := client.stats()["tables"]["all"]["size"]) > 0:
        for ep in client.sample_episodes("all", min(left, 500)):
            assert ep.key not in seen, ep.key  # stored twice
            seen.add(ep.key)
            want = make_episode(ep.actor_id, ep.episode_seq, t=3)
            for name in EPISODE_ARRAYS:
                got, exp = getattr(ep, name), getattr(want, name)
                assert got.dtype == exp.dtype and got.shape == exp.shape, (ep.key, name)
                assert np.asarray(got).tobytes() == exp.tobytes(), (ep.key, name)
            for name in EPISODE_SCALARS:
                assert getattr(ep, name) == getattr(want, name), (ep.key, name)
    client.close()
    assert seen == {(a, s) for a in range(clients) for s in range(per_client)}


def _serve(snap, port: int, port_file, log_file, *extra: str) -> subprocess.Popen:
    """`credit buffer serve` with its log in a file (a pipe could fill and block it)."""
    if port_file.exists():
        port_file.unlink()
    cmd = [sys.executable, "-m", "cluster.cli", "buffer", "serve", "--port", str(port),
           "--port-file", str(port_file), "--snapshot-dir", str(snap), *extra]  # fmt: skip
    with open(log_file, "a") as err:
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=err)
    deadline = time.monotonic() + 30
    while not port_file.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    return proc


def _mount_tmpfs(path, size: str) -> None:
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root (test_storage_full injects the failure)")
    path.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], check=True)


def _fill(path) -> None:
    """Write a filler file until the disk is full."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o644)
    try:
        while os.write(fd, bytes(4096)):
            pass
    except OSError:
        pass
    finally:
        os.close(fd)


@pytest.mark.slow
def test_a_full_disk_refuses_by_name_and_recovers_every_acknowledged_episode(tmp_path):
    disk, port_file, errlog = tmp_path / "disk", tmp_path / "port.json", tmp_path / "serve.log"
    _mount_tmpfs(disk, "4m")
    snap, table = disk / "snap", "name=all,kind=cycling,capacity=2000,max_times_sampled=1"
    args = ("--snapshot-every", "20", "--table", table)
    clients, per_client = 2, 150
    files = [tmp_path / f"acked-{i}.txt" for i in range(clients)]
    procs: list[subprocess.Popen] = []
    proc = _serve(snap, 0, port_file, errlog, *args)
    try:
        port = json.loads(port_file.read_text())["port"]
        cmd = [sys.executable, "-m", "tests.buffer_service.chaos_client", str(port)]
        procs = [
            subprocess.Popen([*cmd, str(i), str(per_client), str(files[i])], cwd=REPO)
            for i in range(clients)
        ]
        while sum(len(_acked(f)[0]) for f in files) < 40:
            time.sleep(0.05)
        _fill(disk / "filler")  # the disk is full from here on
        deadline = time.monotonic() + 60
        while not any(f.exists() and "full" in f.read_text().split() for f in files):
            assert time.monotonic() < deadline, "no insert was refused on a full disk"
            time.sleep(0.05)
        sampler = BufferClient(port=port, schema=SCHEMA)
        sampled = {ep.key for ep in sampler.sample_episodes("all", 5)}  # samples go on
        sampler.close()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) in (0, 1)
        proc = _serve(snap, port, port_file, errlog, *args)  # a restart while still full
        if proc.poll() is not None:  # it may refuse, by name, if it must write to start
            assert proc.returncode == 2
            (disk / "filler").unlink()
            proc = _serve(snap, port, port_file, errlog, *args)
        time.sleep(1.0)  # refused inserts go on being retried meanwhile
        if (disk / "filler").exists():
            (disk / "filler").unlink()  # space returns
        for c in procs:
            assert c.wait(300) == 0
        for f in files:
            seqs, other = _acked(f)
            assert other == ["done"] and seqs == list(range(per_client)), (f, other)
        audit(port, clients, per_client, sampled)
    finally:
        for c in procs:
            c.kill()
        _stop(proc)
        log_text = errlog.read_text()
        report = verify(str(snap))
        subprocess.run(["umount", str(disk)], check=False)
    assert "Traceback" not in log_text, log_text[-3000:]
    assert "storage_full" in log_text  # the refusals and the shutdown named it
    assert report["ok"] and not report["leftovers"], report


@pytest.mark.slow
def test_slow_readers_keep_the_service_within_its_memory_budget(tmp_path):
    """40 authenticated connections ask for 1024 episodes (~38 MB each) and then never read,
    or read a byte every 100 ms; the service's RSS stays within the stored episodes plus
    its reply budget, a normal client's samples stay fast, and the slow ones are cut off."""
    from cluster.bench.common import synthetic_episode
    from cluster.bench.service import SIZES
    from tests.buffer_service.test_requests import Raw, hello

    port_file, errlog, schema = tmp_path / "port.json", tmp_path / "serve.log", SIZES["3m"]
    budget = 96
    proc = _serve(tmp_path / "snap", 0, port_file, errlog, "--table",
                  "name=replay,kind=replay,capacity=2048", "--read-timeout", "4",
                  "--max-inflight-mb", str(budget), "--max-inflight-per-client-mb", "64",
                  "--max-sample", "1024", "--no-fsync")  # fmt: skip
    slow: list[Raw] = []
    try:
        port = json.loads(port_file.read_text())["port"]
        normal = BufferClient(port=port, schema=schema)
        rng = np.random.default_rng(0)
        for i in range(0, 1024, 64):
            normal.insert(
                [synthetic_episode(schema, schema.max_t, 0, rng, i + j) for j in range(64)]
            )
        base = _rss_mb(proc.pid)
        body = codec.pack({"op": "sample", "v": 1, "table": "replay", "batch_size": 1024})
        for i in range(40):
            raw = Raw(port, hello(client=f"slow-{i % 2}"))
            raw.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            raw.sock.sendall(codec.frame(body) + body)
            slow.append(raw)
        peak, lat = base, []
        end = time.monotonic() + 8
        while time.monotonic() < end:
            for raw in slow[::2]:  # half of them read a byte every 100 ms
                with contextlib.suppress(OSError):
                    raw.sock.setblocking(False)
                    raw.sock.recv(1)
            started = time.monotonic()
            normal.sample("replay", 32)
            lat.append(time.monotonic() - started)
            peak = max(peak, _rss_mb(proc.pid))
            time.sleep(0.1)
        normal.close()
    finally:
        for raw in slow:
            raw.close()
        _stop(proc)
    p99 = float(np.percentile(lat, 99))
    print(json.dumps({"rss_base_mb": base, "rss_peak_mb": peak, "sample_p99_s": p99}))
    # beside the stored episodes: the budget, ~1 MiB per connection, interpreter slack
    assert peak - base < budget + 40 + 64, (base, peak)
    assert p99 < 1.0, sorted(lat)[-5:]


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")
