"""The buffer service: an asyncio TCP server of whole episodes (docs/design.md, "Wire protocol").

One event loop owns all state, so request handling needs no locks. An insert's log record is
written and its episodes applied on the loop; its reply waits for an fsync that runs in a
thread and covers every record written before it started (group commit), so "acknowledged
means durable" holds while concurrent inserts share fsyncs (see `buffer_service.storage` for
the guarantee). An episode may be sampled before its insert is acknowledged; if the service
dies in between, the unacknowledged insert is retried by its client. A snapshot copies the
state's references on the loop and is written in a thread, so requests go on meanwhile.

Ops (request fields -> reply fields; every reply has ``ok``):

* ``hello``  {token, schema?} -> {v, schema, tables, max_frame_bytes}. Required first.
* ``insert`` {episodes: [episode], tables?: [name], timeout_s?} -> {inserted, duplicates}.
  All-or-nothing validation; duplicates of ``(actor_id, episode_seq)`` are acknowledged
  and not stored again. Waits for the rate limiter, then ``rate_limited``.
* ``sample`` {table, batch_size, timeout_s?} -> {episodes: [episode]}; waits for the rate
  limiter, then ``rate_limited``.
* ``stats``  {} -> {stats}.   * ``snapshot`` {} -> {path}.

Fields an op does not define are refused (``bad_frame``), and so is anything that cannot be
served correctly (see `buffer_service.requests`), before anything is logged or stored.
Errors reply ``{ok: false, error, message}``; ``frame_too_large``, ``bad_version``,
``auth`` and ``hello_required`` also close the connection. Other clients never notice:
deadlines and limits on reading frames are `buffer_service.connections`'.
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
from buffer_service.config import BufferConfig
from buffer_service.connections import ByteBudget, Conn, FrameTooLargeError
from buffer_service.episode import EpisodeSchema
from buffer_service.metrics import BufferMetrics
from buffer_service.requests import RequestError
from buffer_service.state import BufferState
from buffer_service.storage import Storage

log = logging.getLogger(__name__)

CLOSING_ERRORS = frozenset({"frame_too_large", "bad_version", "auth", "hello_required"})


class GroupCommit:
    """Acknowledge inserts once fsynced, with one fsync for every record written before it
    started. The fsync runs in a thread, so the event loop keeps taking requests meanwhile;
    with a single connection (nothing to group) it runs inline, saving the hand-off.

    Calling pattern (on the event loop)::

        n = storage.append_insert(tables, body)
        await commits.durable(n)        # returns once an fsync (or a snapshot) covered record n
        await commits.idle()            # no fsync in flight (before closing the storage)
    """

    def __init__(self, storage: Storage) -> None:
        self.storage = storage
        self.synced = 0  # the last record number an fsync (or a snapshot) made durable
        self.fsyncs = 0
        self._task: asyncio.Task | None = None

    async def durable(self, record: int, alone: bool = False) -> None:
        """Return once `record` is fsynced. `alone`: no other connection can write meanwhile,
        so there is nothing to group and the fsync runs here, without the thread hand-off."""
        if alone and self._task is None and self.synced < record:
            self.synced = max(self.synced, self.storage.sync())
            self.fsyncs += 1
        while self.synced < record:
            if self._task is None:
                self._task = asyncio.ensure_future(self._sync())
            await asyncio.shield(self._task)

    async def idle(self) -> None:
        while self._task is not None:
            await asyncio.shield(self._task)

    async def _sync(self) -> None:
        try:
            upto = await asyncio.to_thread(self.storage.sync)
            self.synced = max(self.synced, upto)
            self.fsyncs += 1
        finally:
            self._task = None


class BufferServer:
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
        self._conns: set[asyncio.Task] = set()
        self._unauth: dict[asyncio.Task, None] = {}  # no hello yet, oldest first
        self._budget: ByteBudget | None = None
        self._snapshotting: asyncio.Future | None = None
        # Requests the rate limiter held back, per op: [count, seconds waited, timeouts].
        self.limiter_waits: dict[str, list[float]] = {"insert": [0, 0.0, 0], "sample": [0, 0.0, 0]}

    async def start(self) -> None:
        """Restore from the snapshot dir, bind, and start accepting connections."""
        if self.storage is not None:
            self.storage.restore(self.state)
        self._update_sizes()
        self._changed = asyncio.Condition()
        self._budget = ByteBudget(self.cfg.max_inflight_bytes)
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
                await self._snapshot()
            elif self._snapshotting is not None:
                await asyncio.gather(self._snapshotting, return_exceptions=True)
            self.storage.close()
        self.metrics.stop_exporter()

    # ---------------------------------------------------------------- connections

    async def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter):
        task = asyncio.current_task()
        if not self._admit():
            self.metrics.rejected.labels(reason="max_connections").inc()
            writer.close()
            return
        self._conns.add(task)
        self._unauth[task] = None
        try:
            await self._serve_connection(reader, writer, Conn(task, self.cfg))
        except (TimeoutError, ConnectionError, asyncio.IncompleteReadError):
            pass
        except asyncio.CancelledError:
            pass
        except Exception:
            log.exception("buffer connection handler failed")
        finally:
            self._conns.discard(task)
            self._unauth.pop(task, None)
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    def _admit(self) -> bool:
        """Room for one more connection? When full, the oldest connection that has not
        completed its hello is closed to make room; without one the new one is refused."""
        cfg = self.cfg
        if len(self._conns) < cfg.max_connections and len(self._unauth) < cfg.max_unauthenticated:
            return True
        if not self._unauth:
            return False
        oldest = next(iter(self._unauth))
        del self._unauth[oldest]
        oldest.cancel()
        self.metrics.rejected.labels(reason="unauthenticated_evicted").inc()
        return True

    async def _serve_connection(self, reader, writer, conn: Conn) -> None:
        assert self._budget is not None
        while True:
            try:
                async with conn.frame(reader, self._budget) as body:
                    reply = await self._dispatch(body, conn)
            except FrameTooLargeError as e:
                await self._reply(writer, self._error("frame_too_large", str(e)))
                return
            except RequestError as e:
                await self._reply(writer, self._error(e.code, str(e)))
                if e.code in CLOSING_ERRORS:
                    return
                continue
            await self._reply(writer, reply)

    def _error(self, code: str, message: str) -> dict[str, Any]:
        self.metrics.rejected.labels(reason=code).inc()
        log.debug("refused request: %s: %s", code, message)
        return codec.error_reply(code, message)

    async def _reply(self, writer: asyncio.StreamWriter, reply: dict[str, Any]) -> None:
        parts = codec.pack_parts(reply)
        size = sum(memoryview(p).nbytes for p in parts)
        writer.writelines([codec.FRAME_HEADER.pack(size), *parts])
        async with asyncio.timeout(self.cfg.read_timeout_s):  # a client that does not read
            await writer.drain()

    async def _dispatch(self, body: bytes | bytearray, conn: Conn) -> dict[str, Any]:
        try:
            msg = codec.unpack(body)
        except CodecError as e:
            raise RequestError("bad_frame", str(e)) from None
        if msg.get("v") != PROTOCOL_VERSION:
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
            return await self._op_sample(msg)
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
        if msg.get("schema") is not None:
            self._adopt_schema(requests.schema(msg["schema"]))
        conn.hello = True
        self._unauth.pop(conn.task, None)
        schema_d = self.state.schema.to_dict() if self.state.schema else None
        return self._ok(
            schema=schema_d,
            tables=list(self.state.tables),
            max_frame_bytes=self.cfg.max_frame_bytes,
        )

    def _adopt_schema(self, schema: EpisodeSchema) -> None:
        if self.state.schema is None:
            self.state.schema = schema
            if self.storage is not None:
                self.storage.log_schema(schema)
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
            self.storage.append_insert(tables, body)
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
            await self.commits.durable(self.storage.written, alone=len(self._conns) == 1)
        return self._ok(inserted=stored, duplicates=dups)

    async def _op_sample(self, msg: dict[str, Any]) -> dict[str, Any]:
        name, n = requests.sample_args(msg, self.state.tables, self.cfg.max_sample_episodes)
        table = self.state.tables[name]
        timeout = requests.timeout(msg, self.cfg.sample_timeout_s)
        await self._wait(lambda: table.ready(n), timeout, f"sample {n} from {name}", "sample")
        keys = self.state.choose(name, n, self.rng)
        if self.storage is not None:
            self.storage.log_sample(name, keys)
        eps = self.state.apply_sample(name, keys)
        self.metrics.samples.labels(table=name).inc(len(eps))
        self._update_sizes()
        await self._notify()
        return self._ok(episodes=[codec.episode_to_wire(ep) for ep in eps])

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

    def _maybe_snapshot(self) -> None:
        """Start a snapshot in the background when enough inserts were logged since the last."""
        every, st = self.cfg.snapshot_every_inserts, self.storage
        due = st is not None and every and st.records_since_snapshot >= every
        if due and self._snapshotting is None:
            self._start_snapshot()

    def _start_snapshot(self) -> asyncio.Future:
        """Switch the log and copy the state's references here, on the loop (cheap); write
        the file in a thread. Requests go on meanwhile: the inserts they log go to the new
        log, so nothing waits for the snapshot to finish."""
        assert self.storage is not None and self._snapshotting is None
        job = self.storage.begin_snapshot(self.state)
        fut = asyncio.ensure_future(asyncio.to_thread(job.write))
        self._snapshotting = fut
        fut.add_done_callback(self._snapshot_done)
        return fut

    def _snapshot_done(self, fut: asyncio.Future) -> None:
        if self._snapshotting is fut:
            self._snapshotting = None
        if not fut.cancelled() and fut.exception() is not None:
            log.error("snapshot failed (the logs still hold everything): %s", fut.exception())
        elif self._server is not None and self._server.is_serving():
            self._maybe_snapshot()  # became due while this one was written

    async def _snapshot(self) -> str:
        """Snapshot now, after the one in progress if any; returns its path."""
        while self._snapshotting is not None:
            running = self._snapshotting
            await asyncio.gather(running, return_exceptions=True)
            if self._snapshotting is running:
                self._snapshotting = None
        try:
            return await asyncio.shield(self._start_snapshot())
        except OSError as e:
            raise RequestError("internal", f"snapshot failed: {e}") from None

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
        return st
