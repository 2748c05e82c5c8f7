"""The buffer service: an asyncio TCP server of whole episodes (docs/design.md, "Wire protocol").

One event loop owns all state, so request handling needs no locks. An insert's log record is
written and its episodes applied on the loop; its reply waits for an fsync that runs in a
thread and covers every record written before it started (group commit), so "acknowledged
means durable" holds while concurrent inserts share fsyncs (see `buffer_service.storage` for
the guarantee). An episode may be sampled before its insert is acknowledged; if the service
dies in between, the unacknowledged insert is retried by its client. A snapshot copies the
state's references on the loop and is written in a thread, so requests go on meanwhile.

Ops (request fields -> reply fields; every reply has ``ok``):

* ``hello``  {token, schema?, client?} -> {v, schema, tables, max_frame_bytes,
  idle_timeout_s}. Required first; ``client`` names the client (for its connection limit).
* ``insert`` {episodes: [episode], tables?: [name], timeout_s?} -> {inserted, duplicates}.
  All-or-nothing validation; duplicates of ``(actor_id, episode_seq)`` are acknowledged
  and not stored again. Waits for the rate limiter, then ``rate_limited``.
* ``sample`` {table, batch_size, timeout_s?} -> {episodes: [episode]}; waits for the rate
  limiter, then ``rate_limited``.
* ``stats``  {} -> {stats}.   * ``snapshot`` {} -> {path}.

An insert whose log record cannot be written (a full disk) is refused with ``storage_full``
and nothing of it is stored or logged; samples go on (a sample record that cannot be written
is skipped: see `buffer_service.storage` for what that costs). ``v`` must be the integer
`PROTOCOL_VERSION` (``true`` is not 1).

Fields an op does not define are refused (``bad_frame``), and so is anything that cannot be
served correctly (see `buffer_service.requests`), before anything is logged or stored.
Errors reply ``{ok: false, error, message}``; ``frame_too_large``, ``bad_version``,
``auth``, ``hello_required`` and ``too_many_connections`` also close the connection.
Other clients never notice: deadlines and limits of connections, frames and replies are
`buffer_service.connections`'.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import os
import random
import time
from typing import Any

from buffer_service import codec, requests
from buffer_service.codec import PROTOCOL_VERSION, CodecError
from buffer_service.commit import GroupCommit
from buffer_service.config import BufferConfig
from buffer_service.connections import (
    Admission,
    ByteBudget,
    Conn,
    FrameTooLargeError,
    IdleError,
    abort,
    write_frame,
)
from buffer_service.episode import EpisodeSchema
from buffer_service.metrics import BufferMetrics
from buffer_service.packed import PackedEpisode
from buffer_service.requests import RequestError
from buffer_service.scheduling import SnapshotScheduling
from buffer_service.state import BufferState
from buffer_service.storage import Storage, WriteError

log = logging.getLogger(__name__)

CLOSING_ERRORS = frozenset(
    {"frame_too_large", "bad_version", "auth", "hello_required", "too_many_connections"}
)
REPLY_OVERHEAD = 512  # wire bytes of one episode beside its arrays (keys, dtypes, shapes)

__all__ = ["BufferServer", "GroupCommit"]


def reply_bytes(ep: PackedEpisode) -> int:
    """An upper bound of the bytes `ep` takes in a sample reply (its packed buffer)."""
    return REPLY_OVERHEAD + ep.data.nbytes


class BufferServer(SnapshotScheduling):
    """The service on the current event loop: ``await start()``, then ``await close()``.

    Args:
        cfg: validated on construction (ValueError names the bad field, e.g. a
            non-loopback host without a token).
    """

    def __init__(self, cfg: BufferConfig) -> None:
        cfg.validate()
        self.cfg = cfg
        self.state = BufferState(cfg)
        self.storage = None
        if cfg.snapshot_dir:
            self.storage = Storage(cfg.snapshot_dir, cfg.fsync, cfg.repair, cfg.tables)
        self.commits = GroupCommit(self.storage) if self.storage and cfg.fsync else None
        self.metrics = BufferMetrics(list(self.state.tables))
        seed = cfg.seed if cfg.seed is not None else int.from_bytes(os.urandom(8), "little")
        self.rng = random.Random(seed)
        self.port = 0
        self.metrics_port: int | None = None
        self._server: asyncio.base_events.Server | None = None
        self._changed: asyncio.Condition | None = None
        self._admission = Admission(cfg)
        self._conns = self._admission.conns
        self._budget: ByteBudget | None = None
        self.unlogged_samples = 0  # samples served whose record could not be written
        self.close_error: str | None = None  # why the final snapshot was not written
        self._snapshotting: asyncio.Future | None = None
        # Requests the rate limiter held back, per op: [count, seconds waited, timeouts].
        self.limiter_waits: dict[str, list[float]] = {"insert": [0, 0.0, 0], "sample": [0, 0.0, 0]}

    async def start(self) -> None:
        """Restore from the snapshot dir, bind, and start accepting connections."""
        if self.storage is not None:
            self.storage.restore(self.state)
        self._update_sizes()
        self._changed = asyncio.Condition()
        cfg = self.cfg
        self._budget = ByteBudget(cfg.max_inflight_bytes, cfg.max_inflight_bytes_per_client)
        self._server = await asyncio.start_server(
            self._on_connect, self.cfg.host, self.cfg.port, limit=2**16, backlog=1024
        )
        self.port = int(self._server.sockets[0].getsockname()[1])
        if self.cfg.metrics_port is not None:
            self.metrics_port = self.metrics.start_exporter(self.cfg.metrics_port)
        log.info("buffer service listening on %s:%d", self.cfg.host, self.port)

    async def close(self, snapshot: bool = True) -> None:
        """Stop accepting, drop connections, write a final snapshot (if durable)."""
        if self._server is not None:
            self._server.close()
        for task in list(self._conns):
            task.cancel()
        if self._conns:
            await asyncio.gather(*self._conns, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()
        if self.storage is not None:
            if self.commits is not None:
                await self.commits.idle()
            if snapshot:
                await self._final_snapshot()
            elif self._snapshotting is not None:
                await asyncio.gather(self._snapshotting, return_exceptions=True)
            self.storage.close()
        self.metrics.stop_exporter()

    # ---------------------------------------------------------------- connections

    async def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter):
        task = asyncio.current_task()
        admitted, evicted = self._admission.admit(task)
        if evicted:
            self.metrics.rejected.labels(reason="unauthenticated_evicted").inc()
        if not admitted:
            self.metrics.rejected.labels(reason="max_connections").inc()
            abort(writer)
            return
        conn = Conn(task, self.cfg)
        try:
            await self._serve_connection(reader, writer, conn)
        except IdleError:
            self.metrics.rejected.labels(reason="idle").inc()
        except (TimeoutError, ConnectionError, asyncio.IncompleteReadError):
            abort(writer)  # (a reply's transport is aborted already)
        except asyncio.CancelledError:
            abort(writer)
        except Exception:
            log.exception("buffer connection handler failed")
            abort(writer)
        finally:
            self._admission.leave(conn)
            self._release_reply(conn)
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    async def _serve_connection(self, reader, writer, conn: Conn) -> None:
        assert self._budget is not None
        while True:
            try:
                async with conn.frame(reader, self._budget) as body:
                    reply = await self._dispatch(body, conn)
            except FrameTooLargeError as e:
                await self._reply(writer, self._error("frame_too_large", str(e)), conn)
                return
            except RequestError as e:
                await self._reply(writer, self._error(e.code, str(e)), conn)
                if e.code in CLOSING_ERRORS:
                    return
                continue
            await self._reply(writer, reply, conn)

    def _error(self, code: str, message: str) -> dict[str, Any]:
        self.metrics.rejected.labels(reason=code).inc()
        log.debug("refused request: %s: %s", code, message)
        return codec.error_reply(code, message)

    async def _reply(self, writer, reply: dict[str, Any], conn: Conn) -> None:
        """Write `reply` (aborting the connection if the client does not take it within
        read_timeout_s), then give back the budget share a sample reply held."""
        try:
            await write_frame(writer, codec.pack_parts(reply), self.cfg.read_timeout_s)
        finally:
            self._release_reply(conn)

    def _release_reply(self, conn: Conn) -> None:
        if conn.reply_bytes and self._budget is not None:
            self._budget.give(conn.reply_bytes, conn.client)
            conn.reply_bytes = 0

    async def _dispatch(self, body: bytes | bytearray, conn: Conn) -> dict[str, Any]:
        try:
            msg = codec.unpack(body)
        except CodecError as e:
            raise RequestError("bad_frame", str(e)) from None
        if type(msg.get("v")) is not int or msg["v"] != PROTOCOL_VERSION:
            raise RequestError(
                "bad_version",
                f"protocol version {msg.get('v')!r}, server speaks {PROTOCOL_VERSION}",
            )
        op = msg.get("op")
        requests.check_fields(op, msg)
        if op == "hello":
            return self._op_hello(msg, conn)
        if not conn.hello:
            raise RequestError("hello_required", f"op {op!r} before a successful hello")
        if op == "insert":
            return await self._op_insert(msg, body)
        if op == "sample":
            return await self._op_sample(msg, conn)
        if op == "stats":
            return self._ok(stats=self.stats())
        if self.storage is None:  # op == "snapshot"
            raise RequestError("bad_request", "server has no snapshot_dir")
        return self._ok(path=await self._snapshot())

    @staticmethod
    def _ok(**fields: Any) -> dict[str, Any]:
        return {"ok": True, "v": PROTOCOL_VERSION, **fields}

    # ---------------------------------------------------------------- ops

    def _op_hello(self, msg: dict[str, Any], conn: Conn) -> dict[str, Any]:
        token = msg.get("token")
        if self.cfg.token is not None and not (
            isinstance(token, str) and hmac.compare_digest(token.encode(), self.cfg.token.encode())
        ):
            raise RequestError("auth", "wrong or missing token")
        client = requests.client_id(msg)
        if msg.get("schema") is not None:
            self._adopt_schema(requests.schema(msg["schema"]))
        self._admission.authenticate(conn, client)
        schema_d = self.state.schema.to_dict() if self.state.schema else None
        return self._ok(
            schema=schema_d,
            tables=list(self.state.tables),
            max_frame_bytes=self.cfg.max_frame_bytes,
            idle_timeout_s=self.cfg.idle_timeout_s,
        )

    def _adopt_schema(self, schema: EpisodeSchema) -> None:
        if self.state.schema is None:
            self.state.schema = schema
            if self.storage is not None:
                try:
                    self.storage.log_schema(schema)
                except WriteError as e:
                    self.state.schema = None
                    raise RequestError(e.code, str(e)) from None
            log.info("buffer learned episode schema %s", schema)
        elif schema != self.state.schema:
            raise RequestError(
                "schema_mismatch", f"server holds {self.state.schema}, client sent {schema}"
            )

    async def _op_insert(self, msg: dict[str, Any], body: bytes | bytearray) -> dict[str, Any]:
        if self.state.schema is None:
            raise RequestError("bad_request", "no episode schema yet: send one in hello")
        tables = requests.insert_tables(msg, list(self.state.tables))
        eps = requests.insert_episodes(msg, self.state.schema, len(body))
        timeout = requests.timeout(msg, self.cfg.insert_timeout_s)
        if any(not self.state.is_duplicate(ep.key) for ep in eps):
            await self._wait(
                lambda: all(self.state.tables[t].limiter.can_insert(1) for t in tables),
                timeout,
                f"insert into {tables}",
                "insert",
            )
        fresh = [ep for ep in eps if not self.state.is_duplicate(ep.key)]
        if fresh and self.storage is not None:
            try:
                self.storage.append_insert(tables, body, len(eps))
            except WriteError as e:  # rolled back: nothing of it stored or logged
                raise RequestError(e.code, str(e)) from None
        stored = sum(self.state.insert(ep, tables) for ep in eps)
        dups = len(eps) - stored
        for t in tables:
            self.metrics.inserts.labels(table=t).inc(stored)
        if dups:
            self.metrics.rejected.labels(reason="duplicate").inc(dups)
        self._update_sizes()
        await self._notify()
        self._maybe_snapshot()
        if self.commits is not None:
            # Acknowledged only once fsynced; a duplicate too, as its first insert may still be
            # waiting for its fsync.
            try:
                await self.commits.durable(self.storage.written, alone=len(self._conns) == 1)
            except WriteError as e:
                raise RequestError(e.code, str(e)) from None
        return self._ok(inserted=stored, duplicates=dups)

    async def _op_sample(self, msg: dict[str, Any], conn: Conn) -> dict[str, Any]:
        name, n = requests.sample_args(msg, self.state.tables, self.cfg.max_sample_episodes)
        timeout = requests.timeout(msg, self.cfg.sample_timeout_s)
        keys = await self._choose_within_budget(name, n, timeout, conn)
        if self.storage is not None:
            try:
                self.storage.log_sample(name, keys)
            except WriteError as e:  # served anyway; see storage's guarantee
                self.unlogged_samples += 1
                log.warning("sample from %s served without its log record: %s", name, e)
        eps = self.state.apply_sample(name, keys)
        self.metrics.samples.labels(table=name).inc(len(eps))
        self._update_sizes()
        await self._notify()
        return self._ok(episodes=[codec.episode_to_wire(ep) for ep in eps])

    async def _choose_within_budget(self, name: str, n: int, timeout: float, conn: Conn):
        """Wait for the rate limiter, choose `n` keys, and take the reply's bytes from the
        budget (held until the reply is written); when they do not fit, wait for room and
        choose again. RequestError ``rate_limited`` when `timeout` passes first."""
        assert self._budget is not None
        table = self.state.tables[name]
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            left = max(deadline - loop.time(), 0.0)
            await self._wait(lambda: table.ready(n), left, f"sample {n} from {name}", "sample")
            keys = self.state.choose(name, n, self.rng)
            size = sum(reply_bytes(self.state.episodes[k]) for k in keys)
            if size > self._budget.per_key:
                raise RequestError(
                    "bad_request",
                    f"a sample of {n} episodes from {name} is {size} bytes, above "
                    f"max_inflight_bytes_per_client={self._budget.per_key}: ask for fewer",
                )
            if self._budget.try_take(size, conn.client):
                conn.reply_bytes = size
                return keys
            try:
                async with asyncio.timeout_at(deadline):
                    await self._budget.wait_room(size, conn.client)
            except TimeoutError:
                raise RequestError(
                    "rate_limited",
                    f"sample {n} from {name}: replies in flight held max_inflight_bytes "
                    f"for {timeout:g} s",
                ) from None

    async def _wait(self, ready, timeout: float, what: str, op: str) -> None:
        """Wait until `ready()` (the rate limiter allows `op`), counting held-back requests."""
        assert self._changed is not None
        async with self._changed:
            if ready():
                return
            waits = self.limiter_waits[op]
            waits[0] += 1
            started = time.monotonic()
            try:
                await asyncio.wait_for(self._changed.wait_for(ready), timeout)
            except TimeoutError:
                waits[2] += 1
                raise RequestError(
                    "rate_limited", f"{what}: rate limiter did not allow it within {timeout:g} s"
                ) from None
            finally:
                waits[1] += time.monotonic() - started

    async def _notify(self) -> None:
        assert self._changed is not None
        async with self._changed:
            self._changed.notify_all()

    def _update_sizes(self) -> None:
        for name, t in self.state.tables.items():
            self.metrics.size.labels(table=name).set(len(t))

    def stats(self) -> dict[str, Any]:
        """Table sizes and counters, episodes stored, connections, log generation, and the
        requests the rate limiter held back (`limiter_waits`: per op, how many, the seconds
        they waited in total, and how many timed out), and how many fsyncs acknowledged
        how many insert records (`log_fsyncs`, `log_inserts`; group commit when fewer)."""
        st = self.state.stats()
        st["limiter_waits"] = {
            op: {"count": int(c), "seconds": round(s, 6), "timeouts": int(t)}
            for op, (c, s, t) in self.limiter_waits.items()
        }
        st["connections"] = len(self._conns)
        st["generation"] = self.storage.gen if self.storage else None
        st["log_inserts"] = self.storage.written if self.storage else 0
        st["log_fsyncs"] = self.commits.fsyncs if self.commits else 0
        st["log_bytes"] = self.storage.size if self.storage else 0
        st["unlogged_samples"] = self.unlogged_samples
        assert self._budget is not None
        st["inflight_bytes"] = self._budget.used
        return st
