"""No client, authenticated or not, exhausts the service's memory or connections (issue 40):
replies are bounded and aborted when not read, in-flight replies hold the byte budget,
one client's connections are limited, idle ones are closed (the client reconnects
transparently), and ``v`` must be the integer protocol version."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import threading
import time

import pytest

from buffer_service import codec
from buffer_service.client import BufferClient, BufferServiceError
from buffer_service.episode import EPISODE_ARRAYS, EpisodeSchema
from tests.buffer_service.conftest import make_episode, table
from tests.buffer_service.test_requests import Raw, hello

V = codec.PROTOCOL_VERSION
BIG = EpisodeSchema(n_agents=8, obs_dim=256, state_dim=256, n_actions=4, max_t=60)  # ~0.6 MB
MB = 1 << 20


def big_server(serve, **kw):
    kw.setdefault("tables", (table("replay", "replay", capacity=64),))
    srv, c = serve(schema=BIG, **kw)
    for i in range(16):
        c.insert([make_episode(0, i, t=60, schema=BIG)])
    return srv, c


def ask_sample(raw: Raw, n: int) -> None:
    """Send a sample request and read nothing back."""
    body = codec.pack({"op": "sample", "v": V, "table": "replay", "batch_size": n})
    raw.sock.sendall(codec.frame(body) + body)


def drain(sock: socket.socket) -> int:
    """Read until the server closes or resets the connection; bytes read."""
    got = 0
    sock.settimeout(10)
    try:
        while chunk := sock.recv(1 << 20):
            got += len(chunk)
    except ConnectionResetError:
        pass
    return got


def test_v_true_is_not_protocol_version_1(serve):
    srv, _ = serve()
    raw = Raw(srv.port)
    try:
        reply = raw.ask({"op": "hello", "v": True})
        assert reply["error"] == "bad_version" and "True" in reply["message"]
    finally:
        raw.close()


def test_a_reply_the_client_does_not_take_is_aborted_with_its_buffers(serve):
    srv, c = big_server(serve, read_timeout_s=0.5)
    raw = Raw(srv.port, hello())
    try:
        raw.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        ask_sample(raw, 16)  # ~10 MB of reply, and the client reads none of it
        time.sleep(1.5)  # past read_timeout_s: the server gives up on it
        got = drain(raw.sock)
        ep = make_episode(0, 0, t=60, schema=BIG)
        reply = 16 * sum(getattr(ep, f).nbytes for f in EPISODE_ARRAYS)
        assert got < reply / 2, (got, reply)  # aborted: the rest was dropped, not flushed
        assert c.stats()["inflight_bytes"] == 0  # and its share of the budget given back
    finally:
        raw.close()


def test_replies_in_flight_hold_the_byte_budget_per_client(serve):
    """Two slow readers of one client: the second reply is not even produced while the
    first holds the client's share; another client is served meanwhile."""
    srv, c = big_server(
        serve,
        max_frame_bytes=MB,
        max_inflight_bytes=16 * MB,
        max_inflight_bytes_per_client=8 * MB,
        read_timeout_s=5.0,
    )
    slow = [Raw(srv.port, hello(client="slow")) for _ in range(2)]
    try:
        for raw in slow:
            raw.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            ask_sample(raw, 10)  # ~6 MB each: one fits the client's 8 MB share
        time.sleep(0.5)
        st = c.stats()
        assert st["tables"]["replay"]["samples"] == 10  # the second sample waits, unchosen
        assert 0 < st["inflight_bytes"] <= 8 * MB
        started = time.monotonic()
        assert c.sample("replay", 4).batch_size == 4  # another client: its own share
        assert time.monotonic() - started < 1.0
        with pytest.raises(BufferServiceError, match="max_inflight_bytes_per_client"):
            c.sample("replay", 16)  # a reply above a client's share is refused outright
    finally:
        for raw in slow:
            raw.close()


def test_one_client_cannot_take_every_connection(serve):
    srv, _ = serve(token="t", max_connections=16, max_connections_per_client=4)
    hog, refused = [], 0
    try:
        for _ in range(16):  # one client id, sixteen connections
            raw = Raw(srv.port)
            reply = raw.ask(hello(token="t", client="hog"))
            if reply["ok"]:
                hog.append(raw)
            else:
                assert reply["error"] == "too_many_connections" and "hog" in reply["message"]
                assert raw.ask({"op": "stats", "v": V}) == "closed"
                refused += 1
                raw.close()
        assert (len(hog), refused) == (4, 12)
        started = time.monotonic()
        other = BufferClient(port=srv.port, token="t", max_retries=0)
        try:
            assert other.stats()["connections"] == 5
        finally:
            other.close()
        assert time.monotonic() - started < 1.0
    finally:
        for raw in hog:
            raw.close()


def test_idle_authenticated_connections_are_closed_and_clients_reconnect_quietly(serve, caplog):
    srv, c = serve(idle_timeout_s=0.4)
    raw = Raw(srv.port, hello())
    try:
        assert c.insert([make_episode(0, 0)])["inserted"] == 1
        time.sleep(0.8)  # a learner in a long evaluation
        assert raw.ask({"op": "stats", "v": V}) == "closed"  # the server closed the idle one
        with caplog.at_level(logging.WARNING, logger="buffer_service.client"):
            assert c.sample("replay", 1).batch_size == 1  # carries on as if nothing happened
            assert c.stats()["connections"] == 1
        assert not [r for r in caplog.records if r.name == "buffer_service.client"]
        assert c.reconnects == 2
    finally:
        raw.close()


def test_a_client_whose_connection_the_server_closed_reconnects_without_a_retry(serve, caplog):
    _, c = serve(idle_timeout_s=0.4)
    c.stats()
    c.idle_timeout_s = float("inf")  # only the closed socket tells it
    time.sleep(0.8)
    with caplog.at_level(logging.WARNING, logger="buffer_service.client"):
        assert c.stats()["connections"] == 1
    assert not [r for r in caplog.records if r.name == "buffer_service.client"]


@pytest.mark.slow
def test_authenticated_clients_get_in_within_1s_under_unauthenticated_churn(tmp_path):
    """A real `credit buffer serve`; stalled sockets opened as fast as two threads can (each
    closing the oldest of the unauthenticated ones, the newest 300 kept open) while clients
    with the token connect: each is served within 1 s (with the client's own retries: one
    whose connection was evicted before its hello was processed reconnects after 50 ms)."""
    from tests.buffer_service.test_chaos import _serve
    from tests.buffer_service.test_durability import _stop

    port_file = tmp_path / "port.json"
    proc = _serve(tmp_path / "snap", 0, port_file, tmp_path / "serve.log", "--token", "t")
    port = json.loads(port_file.read_text())["port"]
    stop, opened = threading.Event(), []

    def churn() -> None:
        while not stop.is_set():
            with contextlib.suppress(OSError):
                opened.append(socket.create_connection(("127.0.0.1", port), timeout=5))
            if len(opened) > 300:  # keep the newest 300
                opened.pop(0).close()

    threads = [threading.Thread(target=churn) for _ in range(2)]
    for th in threads:
        th.start()
    times, failed = [], 0
    try:
        time.sleep(0.5)
        for i in range(60):
            started = time.monotonic()
            c = BufferClient(port=port, token="t", client_id=f"c{i}")  # its own retries
            try:
                c.stats()
                times.append(time.monotonic() - started)
            except (ConnectionError, BufferServiceError):
                failed += 1
            finally:
                c.close()
    finally:
        stop.set()
        for th in threads:
            th.join()
        for s in opened:
            s.close()
        _stop(proc)
    assert failed == 0 and max(times) < 1.0, (failed, sorted(times)[-5:])


def test_a_second_hello_moves_the_connection_to_its_new_client(serve):
    srv, _ = serve(max_connections_per_client=1)
    raw = Raw(srv.port, hello(client="a"))
    try:
        assert raw.ask(hello(client="b"))["ok"] is True
        other = Raw(srv.port, hello(client="a"))  # "a" holds none now
        other.close()
        refused = Raw(srv.port)
        assert refused.ask(hello(client="b"))["error"] == "too_many_connections"
        refused.close()
    finally:
        raw.close()
