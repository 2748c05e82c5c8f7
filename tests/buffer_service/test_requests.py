"""Requests that cannot be served correctly are refused, naming the field, before anything
is logged or stored (issue 14): table lists, unknown fields, schemas, impossible episodes,
oversized samples; and a stored episode holds only its own bytes."""

from __future__ import annotations

import math
import socket

import numpy as np
import pytest

from buffer_service import codec
from buffer_service.client import BufferServiceError
from buffer_service.config import BufferConfig
from buffer_service.episode import Episode, EpisodeError
from buffer_service.state import BufferState
from tests.buffer_service.conftest import SCHEMA, make_episode, table

V = codec.PROTOCOL_VERSION


class Raw:
    """One raw connection: send request maps, read reply maps (or "closed")."""

    def __init__(self, port: int, hello: dict | None = None) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        if hello is not None:
            assert self.ask(hello)["ok"] is True

    def ask(self, msg: dict):
        body = codec.pack(msg)
        self.sock.sendall(codec.frame(body) + body)
        head = self._recv(4)
        if head is None:
            return "closed"
        body = self._recv(codec.FRAME_HEADER.unpack(head)[0])
        return "closed" if body is None else codec.unpack(body)

    def _recv(self, n: int) -> bytes | None:
        buf = b""
        while len(buf) < n:
            try:
                chunk = self.sock.recv(n - len(buf))
            except ConnectionResetError:
                return None
            if not chunk:
                return None
            buf += chunk
        return buf

    def close(self) -> None:
        self.sock.close()


def hello(**kw) -> dict:
    return {"op": "hello", "v": V, **kw}


def insert(eps: list[Episode], **kw) -> dict:
    return {"op": "insert", "v": V, "episodes": [codec.episode_to_wire(e) for e in eps], **kw}


@pytest.fixture
def durable(serve, tmp_path):
    """A server with a log: (server thread, client, function giving the log's size)."""
    srv, c = serve(snapshot_dir=str(tmp_path), snapshot_every_inserts=0)
    c.stats()  # connected; the log holds its file record

    def log_size() -> int:
        return (tmp_path / "log-00000000.bin").stat().st_size

    return srv, c, log_size


@pytest.mark.parametrize(
    ("tables", "code", "words"),
    [
        (["replay", "replay"], "bad_request", "more than once"),
        ([], "bad_request", "is empty"),
        (["replay", "nope"], "no_table", "nope"),
    ],
)
def test_bad_table_lists_are_refused_before_logging(durable, tables, code, words):
    _, c, log_size = durable
    before = log_size()
    with pytest.raises(BufferServiceError, match=rf"{code}: tables.*{words}"):
        c.insert([make_episode(0, 0)], tables=tables)
    assert log_size() == before and c.stats()["episodes_stored"] == 0
    # the refused insert did not mark the episode as seen: the real one is stored
    assert c.insert([make_episode(0, 0)], tables=["replay"]) == {"inserted": 1, "duplicates": 0}
    assert c.stats()["tables"]["replay"]["size"] == 1


def test_a_table_listed_twice_in_an_old_log_is_held_once():
    # What the old server stored for tables=["cycling", "cycling"]: restoring its log, then
    # evicting the episode, raised KeyError and kept the service from starting.
    state = BufferState(BufferConfig(tables=(table("cycling", "cycling", capacity=2, k=1),)))
    state.insert(make_episode(0, 0), ["cycling", "cycling"])
    assert list(state.tables["cycling"].order) == [(0, 0)] and state.refs[(0, 0)] == 1
    for seq in (1, 2):
        state.insert(make_episode(0, seq), ["cycling"])
    assert list(state.tables["cycling"].order) == [(0, 1), (0, 2)]
    assert set(state.episodes) == {(0, 1), (0, 2)}


def test_unknown_fields_are_refused_and_not_logged(durable):
    srv, c, log_size = durable
    raw = Raw(srv.port, hello())
    try:
        before = log_size()
        junk = np.zeros(100_000, np.uint8).tobytes()
        reply = raw.ask(insert([make_episode(0, 0)], junk=junk))
        assert reply["ok"] is False and reply["error"] == "bad_frame"
        assert "junk" in reply["message"]
        assert log_size() == before and c.stats()["episodes_stored"] == 0
        for msg in (
            {"op": "stats", "v": V, "extra": 1},
            {"op": "sample", "v": V, "table": "replay", "batch_size": 1, "x": None},
            hello(token=None, debug=True),
        ):
            reply = raw.ask(msg)
            assert reply["error"] == "bad_frame" and "unknown fields" in reply["message"]
        assert raw.ask(insert([make_episode(0, 0)]))["inserted"] == 1  # still served
    finally:
        raw.close()


@pytest.mark.parametrize(
    ("value", "shown"),
    [
        (math.inf, "inf"),
        (-math.inf, "-inf"),
        (math.nan, "nan"),
        (3.5, "3.5"),
        ("3", "'3'"),
        (True, "True"),
        (0, "0"),
        (2**40, str(2**40)),
    ],
)
def test_hello_with_a_bad_schema_value_gets_an_error_reply(serve, value, shown):
    srv, c = serve(schema=None)
    raw = Raw(srv.port)
    try:
        reply = raw.ask(hello(schema=dict(SCHEMA.to_dict(), obs_dim=value)))
        assert reply != "closed" and reply["ok"] is False and reply["error"] == "bad_frame"
        assert "obs_dim" in reply["message"] and shown in reply["message"]
        assert raw.ask(hello(schema=SCHEMA.to_dict()))["ok"] is True  # same connection
    finally:
        raw.close()
    assert c.stats()["schema"] == SCHEMA.to_dict()


def _with(ep: Episode, **arrays) -> Episode:
    return Episode(**{**ep.__dict__, **arrays})


def test_impossible_episodes_are_refused(serve):
    _, c = serve()
    ep = make_episode(0, 0, t=4)
    no_action = ep.avail_actions.copy()
    no_action[2, 1] = 0  # agent 1 can do nothing at step 2
    partly = np.array([1, 1, 0, 1], bool)
    for bad in [_with(ep, filled=np.zeros(4, bool)), _with(ep, filled=partly)]:
        with pytest.raises(EpisodeError, match="filled"):  # the packed form cannot hold them
            c.insert([bad])
    field = "avail_actions': agent 1 .* step 2"
    with pytest.raises(BufferServiceError, match=rf"invalid_episode: episode 0: .*{field}"):
        c.insert([_with(ep, avail_actions=no_action)])
    assert c.stats()["episodes_stored"] == 0
    assert c.insert([ep])["inserted"] == 1


def test_sample_size_above_the_configured_cap_is_refused(serve):
    _, c = serve(max_sample_episodes=8)
    c.insert([make_episode(0, i) for i in range(3)])
    with pytest.raises(BufferServiceError, match=r"bad_request: batch_size 9 .*max_sample"):
        c.sample("replay", 9)
    assert c.sample("replay", 8).batch_size == 8  # with replacement, up to the cap
    assert c.stats()["tables"]["replay"]["samples"] == 8
    with pytest.raises(ValueError, match="max_sample_episodes"):
        BufferConfig(max_sample_episodes=0).validate()


def test_default_sample_cap_refuses_the_issue_example(serve):
    _, c = serve()
    c.insert([make_episode(0, 0)])
    with pytest.raises(BufferServiceError, match="batch_size 8000"):
        c.sample("replay", 8000)


def _held_bytes(arr: np.ndarray) -> int:
    """Bytes of the buffer `arr`'s memory belongs to (a whole frame for a zero-copy view)."""
    base = arr
    while isinstance(base, np.ndarray) and base.base is not None:
        base = base.base
    if isinstance(base, memoryview):
        base = base.obj
    return base.nbytes if isinstance(base, (np.ndarray, memoryview)) else len(base)


def test_a_stored_episode_holds_only_its_own_bytes(serve):
    srv, c = serve(tables=(table("replay", "replay", capacity=1),))
    eps = [make_episode(1, i, t=10) for i in range(4000)]
    frame = len(codec.pack(insert(eps)))
    assert frame >= codec.ZERO_COPY_MIN  # decoded without copying: views of the frame
    assert c.insert(eps)["inserted"] == 4000
    (kept,) = srv.server.state.episodes.values()  # the last one; the frame is gone
    own, held = kept.data.nbytes, _held_bytes(kept.data)  # one packed buffer
    assert held <= 2 * own, (held, own, frame)
