"""No client can starve the others (issue 14): stalled unauthenticated sockets, frame
deadlines, the frame limit before hello, and the byte budget for large bodies."""

from __future__ import annotations

import asyncio
import socket

import pytest

from buffer_service import codec
from buffer_service.client import BufferClient
from buffer_service.connections import ByteBudget
from tests.buffer_service.conftest import make_episode
from tests.buffer_service.test_requests import Raw, hello

TOKEN = "t0ken"


def _closed_by_server(sock: socket.socket) -> bool:
    """Block (up to the socket timeout) until the server closes; True if it did."""
    try:
        while sock.recv(4096):
            pass
        return True
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


def test_authenticated_clients_are_served_while_300_sockets_stall(serve):
    srv, _ = serve(token=TOKEN, hello_timeout_s=600)  # the stalled ones never time out here
    stalled = []
    try:
        for i in range(300):
            s = socket.create_connection(("127.0.0.1", srv.port), timeout=10)
            if i % 2:
                s.sendall(b"\0\0\0")  # most of a frame header, then nothing
            stalled.append(s)
        for actor in range(3):  # each a fresh connection, with the token, no retries
            c = BufferClient(port=srv.port, token=TOKEN, max_retries=0, connect_timeout_s=5)
            try:
                assert c.insert([make_episode(actor, 0)])["inserted"] == 1
                assert c.sample("replay", 1).batch_size == 1
            finally:
                c.close()
        c = BufferClient(port=srv.port, token=TOKEN, max_retries=0)
        st = c.stats()
        c.close()
        assert st["episodes_stored"] == 3
        assert st["connections"] <= srv.server.cfg.max_unauthenticated + 1  # stalled ones gave way
    finally:
        for s in stalled:
            s.close()


def test_a_connection_without_hello_is_closed_after_hello_timeout(serve):
    srv, _ = serve(hello_timeout_s=0.3)
    silent = socket.create_connection(("127.0.0.1", srv.port), timeout=20)
    partial = socket.create_connection(("127.0.0.1", srv.port), timeout=20)
    try:
        partial.sendall(b"\0\0")
        assert _closed_by_server(silent) and _closed_by_server(partial)
    finally:
        silent.close()
        partial.close()


def test_a_started_frame_must_arrive_within_read_timeout(serve):
    srv, c = serve(read_timeout_s=0.3)
    body = codec.pack({"op": "stats", "v": codec.PROTOCOL_VERSION})
    raw, header_only = Raw(srv.port, hello()), Raw(srv.port, hello())
    try:
        for sock, part in [(header_only.sock, 2), (raw.sock, 6)]:
            sock.settimeout(20)
            sock.sendall((codec.frame(body) + body)[:part])  # part of the header / the body
        assert _closed_by_server(header_only.sock) and _closed_by_server(raw.sock)
        idle = Raw(srv.port, hello())  # an authenticated connection may idle between frames
        assert idle.ask({"op": "stats", "v": codec.PROTOCOL_VERSION})["ok"] is True
        idle.close()
        assert c.stats()["connections"] == 1
    finally:
        raw.close()
        header_only.close()


def test_frames_before_hello_are_limited_to_max_hello_bytes(serve):
    srv, c = serve(max_hello_bytes=4096, max_frame_bytes=1 << 20)
    for size in (60 << 20, 4097):
        raw = Raw(srv.port)
        try:
            raw.sock.sendall(codec.FRAME_HEADER.pack(size))  # no body: refused on the header
            head = raw._recv(4)
            reply = codec.unpack(raw._recv(codec.FRAME_HEADER.unpack(head)[0]))
            assert reply["error"] == "frame_too_large" and "max_hello_bytes" in reply["message"]
            assert raw._recv(1) is None  # and closed
        finally:
            raw.close()
    big = [make_episode(0, i) for i in range(40)]  # > 4096 bytes, after hello: fine
    assert c.insert(big)["inserted"] == 40


def test_byte_budget_holds_large_bodies_back_until_memory_is_freed():
    async def scenario() -> list[str]:
        budget, order = ByteBudget(100), []

        async def body(name: str, n: int, release: asyncio.Event) -> None:
            async with budget.hold(n):
                order.append(f"{name} in")
                await release.wait()
            order.append(f"{name} out")

        first, second = asyncio.Event(), asyncio.Event()
        a = asyncio.ensure_future(body("a", 70, first))
        await asyncio.sleep(0)
        b = asyncio.ensure_future(body("b", 40, second))
        for _ in range(5):
            await asyncio.sleep(0)
        assert budget.used == 70 and order == ["a in"]  # b waits: 70 + 40 > 100
        first.set()
        second.set()
        await asyncio.gather(a, b)
        return order

    assert asyncio.run(scenario()) == ["a in", "a out", "b in", "b out"]


@pytest.mark.parametrize("field", ["max_hello_bytes", "max_inflight_bytes"])
def test_limits_are_checked_against_max_frame_bytes(field):
    from buffer_service.config import BufferConfig

    bad = {"max_hello_bytes": 2 << 20, "max_inflight_bytes": (1 << 20) - 1}[field]
    with pytest.raises(ValueError, match=field):
        BufferConfig(max_frame_bytes=1 << 20, **{field: bad}).validate()


def test_a_new_clients_first_insert_is_split_by_the_servers_frame_limit(serve):
    """A client that has not connected yet still sizes its first insert's frames by the
    server's max_frame_bytes (learnt from the hello), not by its own default of 64 MiB."""
    srv, c = serve(max_frame_bytes=1 << 20)
    eps = [make_episode(0, i) for i in range(2500)]  # about 1.5 MB packed in all
    fresh = BufferClient("127.0.0.1", srv.port, max_retries=0)
    try:
        assert fresh.insert(eps) == {"inserted": 2500, "duplicates": 0}
    finally:
        fresh.close()
    assert c.stats()["tables"]["replay"]["size"] == 2500
