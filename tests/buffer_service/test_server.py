"""The real server over real TCP on 127.0.0.1: tables, limiter, idempotency, auth, metrics."""

from __future__ import annotations

import threading
import time
import urllib.request

import numpy as np
import pytest

from buffer_service.client import AuthError, BufferClient, BufferServiceError, RateLimitedError
from buffer_service.config import BufferConfig
from buffer_service.episode import EpisodeSchema
from buffer_service.runner import start_server_thread
from buffer_service.server import BufferServer
from tests.buffer_service.conftest import SCHEMA, make_episode, table


def seqs(batch) -> list[int]:
    return sorted(int(s) for s in batch.episode_seq)


def test_cycling_drops_oldest_and_honours_k(serve):
    _, c = serve(tables=(table("cycling", "cycling", capacity=4, k=2),))
    assert c.insert([make_episode(0, i) for i in range(6)]) == {"inserted": 6, "duplicates": 0}
    assert c.stats()["tables"]["cycling"]["size"] == 4
    first = c.sample("cycling", 4)
    assert seqs(first) == [2, 3, 4, 5]  # oldest two dropped on overflow
    assert seqs(c.sample("cycling", 4)) == [2, 3, 4, 5]
    assert c.stats()["tables"]["cycling"]["size"] == 0  # each sampled K=2 times, retired
    with pytest.raises(RateLimitedError):
        c.sample("cycling", 1, timeout_s=0.2)
    c.insert([make_episode(0, 9, t=3)])
    assert seqs(c.sample("cycling", 1)) == [9]


def test_sampled_batch_matches_inserted_episodes(serve):
    _, c = serve(tables=(table("cycling", "cycling", capacity=8, k=1),))
    eps = {i: make_episode(1, i, t=2 + i) for i in range(4)}
    c.insert(list(eps.values()))
    b = c.sample("cycling", 4)
    assert b.obs.shape == (4, 6, SCHEMA.n_agents, SCHEMA.obs_dim)  # padded to T = 5
    assert b.actions.shape == (4, 5, SCHEMA.n_agents) and b.filled.shape == (4, 5)
    for row in range(4):
        ep = eps[int(b.episode_seq[row])]
        t = ep.length
        np.testing.assert_array_equal(b.obs[row, : t + 1], ep.obs)
        np.testing.assert_array_equal(b.actions[row, :t], ep.actions)
        assert b.filled[row].sum() == t and int(b.actor_id[row]) == 1
        assert int(b.policy_version[row]) == ep.policy_version


def test_replay_uniform_and_capacity(serve):
    _, c = serve(tables=(table("replay", "replay", capacity=5),))
    c.insert([make_episode(0, i) for i in range(8)])
    assert c.stats()["tables"]["replay"]["size"] == 5
    got = [s for _ in range(4) for s in seqs(c.sample("replay", 50))]
    assert set(got) == {3, 4, 5, 6, 7}  # 200 draws with replacement over the newest 5
    assert c.stats()["tables"]["replay"]["size"] == 5  # replay never retires


def test_idempotent_inserts(serve):
    _, c = serve()
    eps = [make_episode(2, i) for i in range(5)]
    assert c.insert(eps) == {"inserted": 5, "duplicates": 0}
    assert c.insert([*eps[:3], make_episode(2, 5)]) == {"inserted": 1, "duplicates": 3}
    assert c.insert([make_episode(3, 0), make_episode(3, 0)]) == {"inserted": 1, "duplicates": 1}
    st = c.stats()
    assert st["episodes_stored"] == 7 and st["duplicates"] == 4
    assert st["tables"]["replay"]["inserts"] == 7


def test_insert_into_named_tables_only(serve):
    _, c = serve()
    c.insert([make_episode(0, 0)], tables=["replay"])
    st = c.stats()["tables"]
    assert st["replay"]["size"] == 1 and st["cycling"]["size"] == 0
    with pytest.raises(BufferServiceError, match="no_table"):
        c.insert([make_episode(0, 1)], tables=["nope"])
    with pytest.raises(BufferServiceError, match="no_table"):
        c.sample("nope", 1)


def test_rate_limiter_blocks_and_releases(serve):
    rl = {"min_size_to_sample": 2, "samples_per_insert": 1, "error_buffer": 1}
    srv, c = serve(tables=(table("replay", "replay", capacity=100, **rl),), insert_timeout_s=20)
    c.insert([make_episode(0, 0)])
    with pytest.raises(RateLimitedError, match="rate limiter"):
        c.sample("replay", 1, timeout_s=0.2)  # below min_size_to_sample
    c.insert([make_episode(0, 1)])
    c.insert([make_episode(0, 2)])  # diff = 3 = offset + error_buffer: the last allowed
    done = threading.Event()

    def blocked_insert():
        BufferClient(port=srv.port).insert([make_episode(0, 3)])
        done.set()

    started = time.monotonic()
    with pytest.raises(RateLimitedError, match="insert"):
        c.insert([make_episode(0, 3)], timeout_s=0.2)  # its own wait, under the server's 20 s
    assert time.monotonic() - started < 10
    assert c.stats()["tables"]["replay"]["size"] == 3  # refused: nothing stored
    with pytest.raises(BufferServiceError, match="timeout_s"):
        c.insert([make_episode(0, 3)], timeout_s=-1)
    th = threading.Thread(target=blocked_insert)
    th.start()
    assert not done.wait(0.5)  # cannot finish before a sample lowers the ratio
    c.sample("replay", 1)
    th.join(10)
    assert done.is_set() and c.stats()["tables"]["replay"]["size"] == 4


def test_auth(serve):
    srv, c = serve(token="s3cret")
    c.insert([make_episode(0, 0)])
    for bad in (None, "wrong"):
        with pytest.raises(AuthError):
            BufferClient(port=srv.port, token=bad, max_retries=0).stats()
    assert c.stats()["episodes_stored"] == 1


@pytest.mark.parametrize("host", ["0.0.0.0", "192.0.2.1", "::"])
def test_non_loopback_without_token_refuses_to_start(host):
    with pytest.raises(ValueError, match="token"):
        BufferServer(BufferConfig(host=host))
    with pytest.raises(ValueError, match="token"):
        start_server_thread(BufferConfig(host=host, token=None))


def test_schema_learned_checked_and_invalid_episodes(serve):
    srv, _ = serve(schema=None)
    blind = BufferClient(port=srv.port)
    with pytest.raises(BufferServiceError, match="no episode schema"):
        blind.insert([make_episode()])
    c = BufferClient(port=srv.port, schema=SCHEMA)
    c.insert([make_episode(0, 0)])
    assert blind.stats()["schema"] == SCHEMA.to_dict()
    other = EpisodeSchema(n_agents=2, obs_dim=5, state_dim=7, n_actions=4, max_t=10)
    with pytest.raises(BufferServiceError, match="schema_mismatch"):
        BufferClient(port=srv.port, schema=other).stats()
    nan = make_episode(0, 1)
    nan.reward[2] = np.nan
    with pytest.raises(BufferServiceError, match=r"invalid_episode.*NaN"):
        c.insert([make_episode(0, 2), nan])  # all-or-nothing
    wrong_shape = make_episode(0, 3, schema=other)
    with pytest.raises(BufferServiceError, match=r"invalid_episode.*shape"):
        c.insert([wrong_shape])
    assert c.stats()["episodes_stored"] == 1  # and the connection is still usable


def test_one_client_shared_by_threads(serve):
    _, c = serve()
    errors = []

    def work(actor):
        try:
            for i in range(10):
                c.insert([make_episode(actor, i)])
                c.stats()
        except Exception as e:  # surfaced below
            errors.append(e)

    threads = [threading.Thread(target=work, args=(a,)) for a in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert not errors and c.stats()["episodes_stored"] == 40


def test_metrics_exported(serve):
    srv, c = serve(metrics_port=0)
    c.insert([make_episode(0, i) for i in range(3)] + [make_episode(0, 0)])
    c.sample("replay", 2)
    with pytest.raises(BufferServiceError):
        c.sample("replay", 0)
    text = urllib.request.urlopen(f"http://127.0.0.1:{srv.metrics_port}/metrics", timeout=5).read()
    text = text.decode()
    for line in (
        'credit_buffer_inserts_total{table="replay"} 3.0',
        'credit_buffer_inserts_total{table="cycling"} 3.0',
        'credit_buffer_samples_total{table="replay"} 2.0',
        'credit_buffer_size_episodes{table="cycling"} 3.0',
        'credit_buffer_rejected_total{reason="duplicate"} 1.0',
        'credit_buffer_rejected_total{reason="bad_request"} 1.0',
    ):
        assert line in text, line


def test_client_reconnects_after_server_restart(tmp_path):
    srv = start_server_thread(BufferConfig(snapshot_dir=str(tmp_path), schema=SCHEMA))
    port = srv.port
    c = BufferClient(port=port, backoff_s=0.05)
    c.insert([make_episode(0, 0)])
    srv.stop(snapshot=False)
    restarted = threading.Timer(
        0.3,
        lambda: holder.append(
            start_server_thread(BufferConfig(port=port, snapshot_dir=str(tmp_path), schema=SCHEMA))
        ),
    )
    holder: list = []
    restarted.start()
    try:
        assert c.insert([make_episode(0, 0), make_episode(0, 1)])["inserted"] == 1
        assert c.stats()["episodes_stored"] == 2 and c.reconnects >= 2
    finally:
        restarted.join()
        time.sleep(0)
        for s in holder:
            s.stop(snapshot=False)
