"""Hostile input: every bad frame gets an error reply or a closed connection, a
well-behaved client keeps being served during and after, and memory stays bounded."""

from __future__ import annotations

import contextlib
import errno
import gc
import random
import socket
import threading
import tracemalloc

import msgpack
import numpy as np

from buffer_service import codec
from buffer_service.client import BufferClient
from buffer_service.config import BufferConfig
from buffer_service.runner import start_server_thread
from tests.buffer_service.conftest import SCHEMA, make_episode

TOKEN = "fuzz-token"
MAX_FRAME = 1 << 20
MEMORY_BOUND = 8 * 2**20  # traced growth allowed between two identical fuzz rounds


def _frame(msg: dict) -> bytes:
    body = codec.pack(msg)
    return codec.frame(body) + body


def _read_reply(sock: socket.socket):
    try:
        return _read_reply_raw(sock)
    except (ConnectionResetError, BrokenPipeError):
        return "closed"


def _read_reply_raw(sock: socket.socket):
    head = b""
    while len(head) < 4:
        chunk = sock.recv(4 - len(head))
        if not chunk:
            return "closed"
        head += chunk
    (n,) = codec.FRAME_HEADER.unpack(head)
    body = b""
    while len(body) < n:
        chunk = sock.recv(n - len(body))
        if not chunk:
            return "closed"
        body += chunk
    return codec.unpack(body)


def poke(port: int, payload: bytes, hello: dict | None = None):
    """Send `payload` (after an optional hello), half-close, return the first reply."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        try:
            if hello is not None:
                s.sendall(_frame(hello))
                assert _read_reply(s)["ok"] is True
            s.sendall(payload)
            s.shutdown(socket.SHUT_WR)
            return _read_reply(s)
        except (ConnectionResetError, BrokenPipeError):
            return "closed"
        except OSError as e:
            # The server dropped the connection (a reset) before the half-close: shutdown()
            # then says "not connected". Seen once in a fresh clone's `make test`, 2026-12-07.
            if e.errno == errno.ENOTCONN:
                return "closed"
            raise


def hello(token=TOKEN, **kw) -> dict:
    return {"op": "hello", "v": codec.PROTOCOL_VERSION, "token": token, **kw}


def insert_msg(wire: dict | list, **kw) -> dict:
    eps = wire if isinstance(wire, list) else [wire]
    return {"op": "insert", "v": codec.PROTOCOL_VERSION, "episodes": eps, **kw}


def good_wire(seq: int = 0) -> dict:
    """A protocol-1 (dense) episode map, which the service still reads (old logs hold it)."""
    return codec.unpack(codec.pack(codec.dense_to_wire(make_episode(99, seq))))


def packed_wire(seq: int = 0) -> dict:
    return codec.unpack(codec.pack(codec.episode_to_wire(make_episode(99, seq))))


def packed_cases() -> dict[str, dict]:
    """Malformed packed episodes (protocol 2's form)."""
    p = packed_wire()
    data = codec.decode_array(p["data"]).copy()
    nan = data.copy()
    nan[:4] = np.frombuffer(np.float32(np.nan).tobytes(), np.uint8)  # the first obs value
    counts = list(p["obs_counts"])
    counts[3] += 1
    return {
        "packed_nan": dict(p, data=arr(nan)),
        "packed_short": dict(p, data=arr(data[:-3])),
        "packed_counts": dict(p, obs_counts=counts),
        "packed_unknown": dict(p, packing=99),
        "packed_dims_str": dict(p, dims="3,5,7,4"),
        "packed_wrong_agents": dict(p, dims=[4, *p["dims"][1:]]),
    }


def arr(a: np.ndarray) -> dict:
    return codec.encode_array(a)


def structured_cases() -> list[tuple[str, bytes, dict | None]]:
    """(name, payload, hello-first) for every malformed request we can name."""
    w = good_wire()
    t = make_episode().length
    n, o = SCHEMA.n_agents, SCHEMA.obs_dim
    bad_eps = {
        "obs_float64": dict(w, obs=arr(np.zeros((t + 1, n, o)))),
        "obs_object_dtype": dict(w, obs={"dtype": "|O", "shape": [1], "data": b"\0" * 8}),
        "obs_shape_vs_bytes": dict(w, obs=dict(w["obs"], shape=[t + 1, n, o + 1])),
        "obs_wrong_agents": dict(w, obs=arr(np.zeros((t + 1, n + 1, o), np.float32))),
        "actions_out_of_range": dict(w, actions=arr(np.full((t, n), 77, np.int64))),
        "actions_int32": dict(w, actions=arr(np.zeros((t, n), np.int32))),
        "reward_nan": dict(w, reward=arr(np.array([0, np.nan, 0, 0, 0], np.float32))),
        "reward_inf": dict(w, reward=arr(np.array([np.inf, 0, 0, 0, 0], np.float32))),
        "reward_neg_inf": dict(w, reward=arr(np.array([0, 0, 0, 0, -np.inf], np.float32))),
        "state_inf": dict(w, state=arr(np.full((t + 1, SCHEMA.state_dim), np.inf, np.float32))),
        "too_long": dict(w, reward=arr(np.zeros(SCHEMA.max_t + 1, np.float32))),
        "missing_field": {k: v for k, v in w.items() if k != "filled"},
        "seq_not_int": dict(w, episode_seq=1.5),
        "bool_bytes": dict(w, terminated={"dtype": "|b1", "shape": [t], "data": b"\x05" * t}),
        **packed_cases(),
    }
    v = codec.PROTOCOL_VERSION
    cases = [(f"episode:{k}", _frame(insert_msg(e)), hello()) for k, e in bad_eps.items()]
    msgs = {
        "episodes_not_list": insert_msg([]) | {"episodes": 5},
        "episode_is_int": insert_msg([7]),
        "tables_wrong_type": insert_msg(w, tables="replay"),
        "unknown_table": insert_msg(w, tables=["nope"]),
        "unknown_op": {"op": "drop_tables", "v": v},
        "op_missing": {"v": v},
        "op_int": {"op": 3, "v": v},
        "sample_batch_huge": {"op": "sample", "v": v, "table": "replay", "batch_size": 2**40},
        "sample_batch_negative": {"op": "sample", "v": v, "table": "replay", "batch_size": -1},
        "sample_batch_str": {"op": "sample", "v": v, "table": "replay", "batch_size": "8"},
        "sample_no_table": {"op": "sample", "v": v, "table": None, "batch_size": 1},
        "sample_timeout_neg": {"op": "sample", "v": v, "table": "replay", "batch_size": 1}
        | {"timeout_s": -1},
        "insert_timeout_str": insert_msg(w) | {"timeout_s": "1"},
        "insert_timeout_bool": insert_msg(w) | {"timeout_s": True},
        "wrong_version": {"op": "stats", "v": v + 1},
        "version_str": {"op": "stats", "v": str(v)},
    }
    cases += [(f"msg:{k}", _frame(m), hello()) for k, m in msgs.items()]
    cases += [
        ("hello:wrong_token", _frame(hello(token="nope")), None),
        ("hello:int_token", _frame(hello(token=12345)), None),
        ("hello:no_token", _frame(hello(token=None)), None),
        ("hello:wrong_version", _frame(hello() | {"v": 0}), None),
        ("hello:schema_garbage", _frame(hello(schema="x")), None),
        ("hello:schema_keys", _frame(hello(schema={"n_agents": 3})), None),
        ("hello:schema_other", _frame(hello(schema=dict(SCHEMA.to_dict(), obs_dim=6))), None),
        ("no_hello:insert", _frame(insert_msg(w)), None),
        ("huge_length", codec.FRAME_HEADER.pack(0xFFFFFFFF) + b"\0" * 64, None),
        ("just_over_max", codec.FRAME_HEADER.pack(MAX_FRAME + 1), None),
        ("empty_body", codec.FRAME_HEADER.pack(0), None),
        ("deep_nesting", _raw(b"\x91" * 100_000 + b"\xc0"), None),
        ("array_bomb", _raw(b"\xdd\xff\xff\xff\xff"), None),
        ("map_bomb", _raw(b"\xdf\xff\xff\xff\xff"), None),
        ("not_a_map", _raw(msgpack.packb([1, 2, 3])), None),
        ("int_keys", _raw(msgpack.packb({1: "hello"})), None),
    ]
    return cases


def _raw(body: bytes) -> bytes:
    return codec.frame(body) + body


def random_cases(rng: random.Random, count: int) -> list[tuple[str, bytes, dict | None]]:
    cases = []
    valids = [_frame(insert_msg(good_wire(1))), _frame(insert_msg(packed_wire(1)))]
    for i in range(count):
        kind, valid = i % 4, valids[(i // 4) % 2]
        if kind == 0:  # pure random bytes (random length prefix)
            payload = rng.randbytes(rng.randrange(0, 2000))
        elif kind == 1:  # sane prefix, random body
            payload = _raw(rng.randbytes(rng.randrange(0, 2000)))
        elif kind == 2:  # a valid insert frame truncated
            payload = valid[: rng.randrange(0, len(valid))]
        else:  # a valid insert frame with a few flipped bytes
            b = bytearray(valid)
            for _ in range(rng.randrange(1, 8)):
                b[rng.randrange(4, len(b))] = rng.randrange(256)
            payload = bytes(b)
        cases.append((f"random:{kind}:{i}", payload, hello() if kind >= 2 else None))
    return cases


def check(name: str, reply, allow_ok: bool) -> None:
    if reply == "closed":
        return
    assert isinstance(reply, dict), (name, reply)
    if allow_ok and reply.get("ok") is True:
        return
    assert reply.get("ok") is False, (name, reply)
    assert reply.get("error") in codec.ERROR_CODES, (name, reply)


def run_round(port: int, rng: random.Random) -> dict[str, int]:
    outcomes: dict[str, int] = {}
    for name, payload, h in structured_cases() + random_cases(rng, 120):
        reply = poke(port, payload, h)
        check(name, reply, allow_ok=name.startswith("random:3"))
        key = "closed" if reply == "closed" else str(reply.get("error", "ok"))
        outcomes[key] = outcomes.get(key, 0) + 1
        if name.startswith(("episode:", "msg:", "hello:", "no_hello")):
            assert reply != "closed" and reply["ok"] is False, (name, reply)
            if "nan" in name or "inf" in name:
                assert reply["error"] == "invalid_episode", (name, reply)
    return outcomes


def test_fuzz_server_survives_and_memory_stays_bounded():
    cfg = BufferConfig(
        token=TOKEN, schema=SCHEMA, max_frame_bytes=MAX_FRAME, read_timeout_s=2.0,
        sample_timeout_s=2.0,
    )  # fmt: skip
    srv = start_server_thread(cfg)
    good = BufferClient(port=srv.port, token=TOKEN, max_retries=0)
    stop = threading.Event()
    served: list[int] = []
    errors: list[BaseException] = []

    def well_behaved():
        try:
            for seq in range(400):  # bounded in count; stops early when fuzzing is done
                if stop.is_set():
                    break
                assert good.insert([make_episode(1, seq)])["inserted"] == 1
                assert good.sample("replay", 2).batch_size == 2
                served.append(seq)
        except BaseException as e:  # surfaced below
            errors.append(e)

    th = threading.Thread(target=well_behaved)
    th.start()
    try:
        rng = random.Random(1234)
        first = run_round(srv.port, rng)  # warm-up: caches, lazily built objects
        gc.collect()
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
        for _ in range(2):
            run_round(srv.port, rng)
        gc.collect()
        grown = tracemalloc.get_traced_memory()[0] - base
        tracemalloc.stop()
        stop.set()
        th.join(60)
        assert not errors, errors
        assert served, "the well-behaved client was never served"
        assert grown < MEMORY_BOUND, f"traced memory grew by {grown} bytes"
        assert {"frame_too_large", "bad_frame", "invalid_episode", "auth"} <= set(first)
        n = len(served)
        assert good.insert([make_episode(1, 10_000)])["inserted"] == 1  # still served after
        st = good.stats()
        assert st["connections"] == 1  # every fuzz connection was released
        assert st["tables"]["replay"]["inserts"] >= n + 1
    finally:
        stop.set()
        good.close()
        srv.stop(snapshot=False)


def test_connection_limit_refuses_only_when_every_slot_said_hello():
    srv = start_server_thread(BufferConfig(schema=SCHEMA, max_connections=4))
    clients = [BufferClient(port=srv.port, max_retries=0) for _ in range(4)]
    socks = []
    try:
        for c in clients:
            c.stats()  # four connections that completed their hello: the server is full
        extra = socket.create_connection(("127.0.0.1", srv.port), timeout=5)
        socks.append(extra)
        # the server may refuse (reset) the connection before the hello goes out
        with contextlib.suppress(ConnectionResetError, BrokenPipeError):
            extra.sendall(_frame(hello()))
        assert _read_reply(extra) == "closed"
        clients.pop().close()
        # the slot frees once the server sees the close; then stalled sockets (no hello)
        # give way to newcomers instead of locking them out
        retrying = BufferClient(port=srv.port, max_retries=20, backoff_s=0.05)
        clients.append(retrying)
        assert retrying.stats()["connections"] == 4
        clients.pop().close()
        for _ in range(12):
            socks.append(socket.create_connection(("127.0.0.1", srv.port), timeout=5))
            socks[-1].sendall(b"\0\0\0")
        late = BufferClient(port=srv.port, max_retries=0)
        clients.append(late)
        assert late.stats()["tables"]["replay"]["size"] == 0
    finally:
        for s in socks:
            s.close()
        for c in clients:
            c.close()
        srv.stop(snapshot=False)
