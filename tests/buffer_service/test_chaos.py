"""Chaos (issue 14): client processes insert while the service, a real `credit buffer serve`
subprocess on 127.0.0.1, is killed with kill -9 at random moments (snapshots included, as
one is due every 7 inserts); then every acknowledged episode must be held exactly once,
byte for byte."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from buffer_service.client import BufferClient
from buffer_service.episode import EPISODE_ARRAYS, EPISODE_SCALARS
from buffer_service.verify import verify
from tests.buffer_service.conftest import SCHEMA, make_episode
from tests.buffer_service.test_durability import REPO, _serve_cli, _stop

CLIENTS, PER_CLIENT, KILLS = 4, 400, 12
CAPACITY = CLIENTS * PER_CLIENT


def _acked(path) -> tuple[list[int], list[str]]:
    lines = path.read_text().split() if path.exists() else []
    return [int(x) for x in lines if x.isdigit()], [x for x in lines if not x.isdigit()]


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


def audit(port: int) -> None:
    """Drain the K=1 cycling table: each episode comes out once; compare every byte."""
    client = BufferClient(port=port, schema=SCHEMA)
    st = client.stats()
    assert st["episodes_stored"] == CLIENTS * PER_CLIENT
    seen: set[tuple[int, int]] = set()
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
    assert seen == {(a, s) for a in range(CLIENTS) for s in range(PER_CLIENT)}
