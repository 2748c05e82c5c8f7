"""Checking one request before the server acts on it (docs/design.md, "Wire protocol").

Every check here runs before anything is logged, stored or sampled, and a refused request
raises `RequestError` whose message names the offending field. The server only calls these
functions; they read the request map and the server's configuration, never its state.
"""

from __future__ import annotations

import math
from typing import Any

from buffer_service import codec
from buffer_service.codec import CodecError
from buffer_service.episode import Episode, EpisodeError, EpisodeSchema

# The fields each op may carry besides ``op`` and ``v``; anything else is refused, so an
# insert's log record holds exactly what is stored.
OP_FIELDS: dict[str, frozenset[str]] = {
    "hello": frozenset({"token", "schema", "client"}),
    "insert": frozenset({"episodes", "tables", "timeout_s"}),
    "sample": frozenset({"table", "batch_size", "timeout_s"}),
    "stats": frozenset(),
    "snapshot": frozenset(),
}


class RequestError(Exception):
    """A refused request: becomes an error reply with `code` (one of codec.ERROR_CODES)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def check_fields(op: Any, msg: dict[str, Any]) -> None:
    """Refuse an unknown op, or fields the op does not define."""
    if not isinstance(op, str) or op not in OP_FIELDS:
        raise RequestError("unknown_op", f"unknown op {op!r}")
    unknown = set(msg) - OP_FIELDS[op] - {"op", "v"}
    if unknown:
        allowed = sorted(OP_FIELDS[op])
        raise RequestError(
            "bad_frame", f"{op}: unknown fields {sorted(unknown)} (allowed: {allowed})"
        )


def timeout(msg: dict[str, Any], limit: float) -> float:
    """A request's rate-limiter wait: its ``timeout_s``, capped by the server's `limit`."""
    value = msg.get("timeout_s", limit)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
        raise RequestError("bad_request", f"timeout_s {value!r} must be a number >= 0")
    if not math.isfinite(value):
        return limit
    return min(float(value), limit)


MAX_CLIENT_ID = 256


def client_id(msg: dict[str, Any]) -> str:
    """The ``client`` a hello names (``""`` when it names none): a string of at most
    `MAX_CLIENT_ID` characters."""
    value = msg.get("client", "")
    if not isinstance(value, str) or len(value) > MAX_CLIENT_ID:
        raise RequestError("bad_frame", f"client must be a string of <= {MAX_CLIENT_ID} chars")
    return value


def schema(raw: Any) -> EpisodeSchema:
    """The schema a hello carries; every size a finite int >= 1."""
    if not isinstance(raw, dict):
        raise RequestError("bad_frame", f"schema must be a map, got {type(raw).__name__}")
    try:
        return EpisodeSchema.from_dict(raw)
    except (EpisodeError, TypeError, ValueError, OverflowError) as e:
        raise RequestError("bad_frame", f"schema: {e}") from None


def insert_tables(msg: dict[str, Any], have: list[str]) -> list[str]:
    """The tables an insert names: all of `have` when absent, else a non-empty list of
    distinct names the server has."""
    tables = msg.get("tables")
    if tables is None:
        return list(have)
    if not isinstance(tables, list) or not all(isinstance(t, str) for t in tables):
        raise RequestError("bad_frame", "tables must be a list of names")
    if not tables:
        raise RequestError("bad_request", "tables is empty: name at least one table, or omit it")
    if len(set(tables)) != len(tables):
        raise RequestError("bad_request", f"tables {tables} names a table more than once")
    missing = [t for t in tables if t not in have]
    if missing:
        raise RequestError("no_table", f"tables: no tables {missing}; have {have}")
    return tables


def insert_episodes(msg: dict[str, Any], schema_: EpisodeSchema, frame_bytes: int) -> list[Episode]:
    """Decode and validate every episode of an insert (all or nothing). When the frame of
    `frame_bytes` was decoded without copying, each episode is copied out of it, so that a
    stored episode holds only its own bytes (a view would keep the whole frame alive for as
    long as the episode is stored); smaller frames' arrays already own a buffer each."""
    wires = msg.get("episodes")
    if not isinstance(wires, list):
        raise RequestError("bad_frame", "episodes must be a list")
    eps = []
    for i, wire in enumerate(wires):
        try:
            ep = codec.episode_from_wire(wire)  # checks the packed layout
            ep.validate_contents(schema_)
        except (CodecError, EpisodeError) as e:
            raise RequestError("invalid_episode", f"episode {i}: {e}") from None
        eps.append(codec.own(ep) if codec.decodes_as_views(frame_bytes) else ep)
    return eps


def sample_args(msg: dict[str, Any], tables: dict[str, Any], cap: int) -> tuple[str, int]:
    """``(table, batch_size)`` of a sample: a known table and 1 <= batch_size <= the cap
    (`cap`, and a cycling table's capacity, since its batches never repeat an episode)."""
    name, n = msg.get("table"), msg.get("batch_size")
    if not isinstance(name, str) or name not in tables:
        raise RequestError("no_table", f"table: no table {name!r}; have {list(tables)}")
    cfg = tables[name].cfg
    limit = min(cap, cfg.capacity) if cfg.kind == "cycling" else cap
    if type(n) is not int or not 1 <= n <= limit:
        why = "max_sample_episodes" if limit == cap else "the cycling table's capacity"
        raise RequestError("bad_request", f"batch_size {n!r} outside 1..{limit} for {name} ({why})")
    return name, n
