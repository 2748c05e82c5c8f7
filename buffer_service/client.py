"""Synchronous client of the buffer service, with reconnect and idempotent retries.

Typical loops::

    client = BufferClient("127.0.0.1", port, token=tok, schema=schema)   # actor
    client.insert(worker.collect(4))

    batch = client.sample("cycling", 32)                                  # learner
    learner.step(batch)

A request that fails on the transport (refused connection, reset, timeout, server
restart) is retried on a fresh connection with exponential backoff. Retrying an insert is
safe because the server deduplicates on ``(actor_id, episode_seq)``: the episode is stored
at most once and the retry is acknowledged. A retried *sample* may have consumed the lost
reply's episodes (they count towards a cycling table's K); it never duplicates data.

Idle connections: the server closes an authenticated connection idle for its
``idle_timeout_s`` (sent in its hello reply). Before a request the client reconnects,
without a retry or a warning, when its connection has idled that long or the server closed
it, so a learner that pauses (a long evaluation) carries on as if nothing happened. Every
connection names this client in its hello (``client_id``, by default ``host:pid``), which
is what the server's per-client connection limit counts.

Thread safety: one request is in flight per client at a time (an internal lock serialises
callers); give each thread its own client for parallel requests.
"""

from __future__ import annotations

import logging
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from buffer_service import codec
from buffer_service.codec import PROTOCOL_VERSION
from buffer_service.episode import Episode, EpisodeBatch, EpisodeSchema
from buffer_service.packed import PackedEpisode

log = logging.getLogger(__name__)

PER_EPISODE_OVERHEAD = 1024  # msgpack keys, dtype strings, shapes (generous)
# errors after which the server closes the connection
CLOSING = ("auth", "bad_version", "hello_required", "frame_too_large", "too_many_connections")


class BufferServiceError(RuntimeError):
    """The server refused a request; `code` is one of `codec.ERROR_CODES`."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code


class RateLimitedError(BufferServiceError):
    """The rate limiter did not allow the request within its timeout."""


class AuthError(BufferServiceError):
    """Wrong or missing token."""


class _TransportError(Exception):
    """Connection-level failure: the request is retried on a new connection."""


class BufferClient:
    """Client of one buffer server.

    Args:
        host, port: the server's address.
        token: shared secret (required when the server has one).
        schema: episode sizes; sent in hello so the server can learn or check them.
        connect_timeout_s: per connection attempt.
        request_timeout_s: socket timeout of one request beyond any server-side wait.
        max_retries: transport retries per request before giving up (ConnectionError).
        backoff_s, max_backoff_s: first retry delay and its cap (doubling in between).
        max_frame_bytes: largest reply accepted.
        client_id: the client this is, for the server's per-client connection limit
            (default ``host:pid``: the clients of one process count together).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        token: str | None = None,
        schema: EpisodeSchema | None = None,
        connect_timeout_s: float = 5.0,
        request_timeout_s: float = 60.0,
        max_retries: int = 10,
        backoff_s: float = 0.05,
        max_backoff_s: float = 2.0,
        max_frame_bytes: int = 2**32 - 1,
        client_id: str | None = None,
    ) -> None:
        self.host, self.port, self.token = host, port, token
        self.schema = schema
        self.connect_timeout_s = connect_timeout_s
        self.request_timeout_s = request_timeout_s
        self.max_retries = max_retries
        self.backoff_s, self.max_backoff_s = backoff_s, max_backoff_s
        self.max_frame_bytes = max_frame_bytes
        self.server_max_frame = 64 * 2**20  # until the server's hello says
        self.tables: list[str] = []
        self.reconnects = 0
        self.client_id = client_id or f"{socket.gethostname()}:{os.getpid()}"
        self.idle_timeout_s = float("inf")  # the server's, from its hello reply
        self._last_io = 0.0  # when the connection last carried a reply (monotonic)
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()

    # ---------------------------------------------------------------- public API

    def insert(
        self,
        episodes: list[Episode | PackedEpisode],
        tables: list[str] | None = None,
        timeout_s: float | None = None,
        state: bool = True,
    ) -> dict[str, int]:
        """Store `episodes` (durably, once each) in `tables` (None = every table).

        Args:
            episodes: whole episodes, sent packed (`buffer_service.packed`); split into
                frames under the server's size limit. One that cannot be packed (not
                whole) raises EpisodeError before anything is sent.
            tables: table names, or None for all.
            timeout_s: longest wait for the rate limiter per frame (None: the server's
                insert_timeout_s, which also caps it), then RateLimitedError.
            state: send the episodes' state (False: for learners that never read it).

        Returns:
            ``{"inserted": n, "duplicates": d}`` summed over frames; a retried frame's
            episodes that the lost attempt had stored count as duplicates.
        """
        total = {"inserted": 0, "duplicates": 0}
        if not self.reconnects:
            self._connected()  # the hello tells the server's frame limit the chunks must fit
        for chunk in self._chunks([PackedEpisode.pack(ep, state) for ep in episodes]):
            msg: dict[str, Any] = {"op": "insert", "episodes": chunk}
            if tables is not None:
                msg["tables"] = list(tables)
            if timeout_s is not None:
                msg["timeout_s"] = float(timeout_s)
            reply = self._request(msg, extra_timeout=timeout_s)
            total["inserted"] += reply["inserted"]
            total["duplicates"] += reply["duplicates"]
        return total

    def sample_episodes(
        self, table: str, batch_size: int, timeout_s: float | None = None
    ) -> list[PackedEpisode]:
        """Sample `batch_size` whole episodes from `table` (waits for the rate limiter), as
        stored (packed; `EpisodeBatch.from_episodes` decodes them, `unpack` one)."""
        msg: dict[str, Any] = {"op": "sample", "table": table, "batch_size": int(batch_size)}
        if timeout_s is not None:
            msg["timeout_s"] = float(timeout_s)
        reply = self._request(msg, extra_timeout=timeout_s)
        return [codec.episode_from_wire(w) for w in reply["episodes"]]

    def sample(
        self, table: str, batch_size: int, timeout_s: float | None = None, pad_to: int | None = None
    ) -> EpisodeBatch:
        """Sample a padded batch.

        Args:
            table: table name.
            batch_size: episodes B.
            timeout_s: longest server-side wait for the rate limiter (server default if
                None); RateLimitedError after it.
            pad_to: pad time to this many transitions (default: longest episode).

        Returns:
            EpisodeBatch with obs [B, T+1, N, O], actions [B, T, N], filled [B, T], ...
        """
        return EpisodeBatch.from_episodes(
            self.sample_episodes(table, batch_size, timeout_s), pad_to
        )

    def stats(self) -> dict[str, Any]:
        """Server stats: per-table size/inserts/samples, episodes stored, duplicates."""
        return self._request({"op": "stats"})["stats"]

    def snapshot(self) -> str:
        """Force a snapshot (compacting the log); returns its path on the server."""
        return self._request({"op": "snapshot"})["path"]

    def close(self) -> None:
        with self._lock:
            self._drop()

    def __enter__(self) -> BufferClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- internals

    def _chunks(self, episodes: list[PackedEpisode]):
        limit = int(self.server_max_frame * 0.9)
        chunk: list[dict[str, Any]] = []
        size = 0
        for ep in episodes:
            n = PER_EPISODE_OVERHEAD + ep.data.nbytes
            if n > limit:
                raise ValueError(f"episode {ep.key} needs {n} bytes, server frames hold {limit}")
            if chunk and size + n > limit:
                yield chunk
                chunk, size = [], 0
            chunk.append(codec.episode_to_wire(ep))
            size += n
        if chunk:
            yield chunk

    def _request(self, msg: dict[str, Any], extra_timeout: float | None = None) -> dict[str, Any]:
        body = codec.pack_parts({**msg, "v": PROTOCOL_VERSION})
        wait = extra_timeout if extra_timeout is not None else 0.0
        if msg["op"] in ("sample", "insert") and extra_timeout is None:
            wait = 3600.0  # server-side rate-limiter wait is bounded by the server
        return self._connected(lambda: self._exchange(body, self.request_timeout_s + wait))

    def _connected(self, action: Callable[[], Any] = lambda: None) -> Any:
        """`action()` on a live, greeted connection (reconnecting first when there is none
        or it went stale), retried on transport errors with backoff."""
        delay = self.backoff_s
        with self._lock:
            for attempt in range(self.max_retries + 1):
                try:
                    if self._sock is not None and self._stale():
                        self._drop()  # closed or about to be closed for idling: reconnect
                    if self._sock is None:
                        self._connect()
                    return action()
                except (_TransportError, OSError) as e:
                    self._drop()
                    if attempt == self.max_retries:
                        raise ConnectionError(
                            f"buffer {self.host}:{self.port} unreachable after "
                            f"{attempt + 1} attempts: {e}"
                        ) from e
                    log.warning("buffer request failed (%s); retry in %.2fs", e, delay)
                    time.sleep(delay)
                    delay = min(delay * 2, self.max_backoff_s)
        raise AssertionError("unreachable")

    def _stale(self) -> bool:
        """Has the server closed this connection, or is it about to for idling?"""
        assert self._sock is not None
        if time.monotonic() - self._last_io > 0.8 * self.idle_timeout_s:
            return True
        try:
            readable, _, _ = select.select([self._sock], [], [], 0)
            # nothing to read is the normal case; readable between requests means closed
            return bool(readable) and self._sock.recv(1, socket.MSG_PEEK) == b""
        except OSError:
            return True

    def _connect(self) -> None:
        sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        hello: dict[str, Any] = {"op": "hello", "v": PROTOCOL_VERSION, "token": self.token}
        hello["client"] = self.client_id
        if self.schema is not None:
            hello["schema"] = self.schema.to_dict()
        try:
            reply = self._exchange(codec.pack_parts(hello), self.request_timeout_s)
        except BaseException:
            self._drop()
            raise
        if reply.get("schema") is not None:
            self.schema = EpisodeSchema.from_dict(reply["schema"])
        self.server_max_frame = int(reply["max_frame_bytes"])
        self.tables = list(reply["tables"])
        self.idle_timeout_s = float(reply.get("idle_timeout_s", float("inf")))
        self.reconnects += 1

    def _drop(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    def _exchange(self, parts: list[bytes | memoryview], timeout: float) -> dict[str, Any]:
        sock = self._sock
        assert sock is not None
        sock.settimeout(timeout)
        views = [memoryview(p).cast("B") for p in parts]
        size = sum(v.nbytes for v in views)
        if size > self.server_max_frame:
            raise ValueError(f"request of {size} bytes exceeds the server's max frame")
        _send_parts(sock, [memoryview(codec.FRAME_HEADER.pack(size)), *views])
        head = self._recv_exact(codec.FRAME_HEADER.size)
        (length,) = codec.FRAME_HEADER.unpack(head)
        if length > self.max_frame_bytes:
            raise _TransportError(f"reply of {length} bytes exceeds max_frame_bytes")
        try:
            reply = codec.unpack(self._recv_exact(length))
        except codec.CodecError as e:
            raise _TransportError(f"unreadable reply: {e}") from None
        self._last_io = time.monotonic()
        if reply.get("ok") is True:
            return reply
        code, message = str(reply.get("error")), str(reply.get("message"))
        if code in CLOSING:
            self._drop()  # the server closes these connections
        cls = {"rate_limited": RateLimitedError, "auth": AuthError}.get(code, BufferServiceError)
        raise cls(code, message)

    def _recv_exact(self, n: int) -> bytearray:
        assert self._sock is not None
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        while got < n:
            k = self._sock.recv_into(view[got:], n - got)
            if k == 0:
                raise _TransportError("connection closed by the server")
            got += k
        return buf


def _send_parts(sock: socket.socket, views: list[memoryview]) -> None:
    """sendall over several buffers without joining them (scatter-gather sendmsg)."""
    views = [v for v in views if v.nbytes]
    while views:
        sent = sock.sendmsg(views[:256])
        while sent:
            n = views[0].nbytes
            if sent >= n:
                sent -= n
                views.pop(0)
            else:
                views[0] = views[0][sent:]
                sent = 0
