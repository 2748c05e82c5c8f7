"""Connections under deadlines and limits, so that no client can starve others or exhaust
the service's memory or connections.

* A connection that has not completed its hello must do so within ``hello_timeout_s`` of
  connecting and may send frames of at most ``max_hello_bytes``; at most
  ``max_unauthenticated`` such connections exist, a new one closing the oldest, so the
  other ``max_connections - max_unauthenticated`` slots are reserved for authenticated ones.
* A *client* is the ``client`` id its hello names (the project's `BufferClient` sends
  ``host:pid``; a hello without one counts as the client ``""``): it may hold at most
  ``max_connections_per_client`` authenticated connections; a hello beyond that is refused
  (``too_many_connections``) and closed, so one client cannot take every slot.
* An authenticated connection may idle between frames for ``idle_timeout_s``, then it is
  closed (`BufferClient` reconnects transparently); once a frame's first byte has arrived
  the rest of it must arrive within ``read_timeout_s``.
* Bodies above ``max_hello_bytes``, and sample replies, hold a share of
  ``max_inflight_bytes`` (at most ``max_inflight_bytes_per_client`` per client) while they
  are read, handled or written; further ones wait. Request bodies are read into one buffer
  of exactly their size; replies are written from the episodes' own memory in pieces of at
  most `WRITE_CHUNK` bytes, never joined into one copy, and a reply not taken by the client
  within ``read_timeout_s`` aborts the connection, freeing its transport and buffers.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
from collections.abc import AsyncIterator

from buffer_service import codec
from buffer_service.config import BufferConfig
from buffer_service.requests import RequestError

CHUNK = 1 << 20  # bodies above this are read piecewise into a buffer of their own size
WRITE_CHUNK = 1 << 20  # replies are handed to the transport in pieces of at most this


class FrameTooLargeError(Exception):
    def __init__(self, length: int, limit: int, field: str) -> None:
        super().__init__(f"frame of {length} bytes exceeds {field}={limit}")


class IdleError(Exception):
    """An authenticated connection sent nothing for idle_timeout_s."""


class ByteBudget:
    """Bytes of large request bodies and replies held at once: at most `limit` over all
    connections and `per_key` per client."""

    def __init__(self, limit: int, per_key: int | None = None) -> None:
        self.limit = limit
        self.per_key = limit if per_key is None else per_key
        self.used = 0
        self.by_key: dict[str, int] = {}
        self._waiters: list[asyncio.Future] = []

    def fits(self, n: int, key: str = "") -> bool:
        return self.used + n <= self.limit and self.by_key.get(key, 0) + n <= self.per_key

    def try_take(self, n: int, key: str = "") -> bool:
        if not self.fits(n, key):
            return False
        self.used += n
        self.by_key[key] = self.by_key.get(key, 0) + n
        return True

    async def wait_room(self, n: int, key: str = "") -> None:
        """Return once `n` bytes fit (they are not taken: `try_take` them)."""
        while not self.fits(n, key):
            fut = asyncio.get_running_loop().create_future()
            self._waiters.append(fut)
            await fut

    def give(self, n: int, key: str = "") -> None:
        self.used -= n
        left = self.by_key[key] - n
        if left:
            self.by_key[key] = left
        else:
            del self.by_key[key]
        waiters, self._waiters = self._waiters, []
        for fut in waiters:
            if not fut.done():
                fut.set_result(None)

    @contextlib.asynccontextmanager
    async def hold(self, n: int, key: str = "") -> AsyncIterator[None]:
        while not self.try_take(n, key):
            await self.wait_room(n, key)
        try:
            yield
        finally:
            self.give(n, key)


class Conn:
    """One client connection: whether it said hello (and as which client), by when it
    must, and the reply bytes it holds of the budget."""

    def __init__(self, task: asyncio.Task | None, cfg: BufferConfig) -> None:
        self.task = task
        self.cfg = cfg
        self.hello = False
        self.client = ""
        self.reply_bytes = 0
        self.hello_deadline = asyncio.get_running_loop().time() + cfg.hello_timeout_s

    def frame(self, reader: asyncio.StreamReader, budget: ByteBudget) -> _Frame:
        """``async with conn.frame(reader, budget) as body``: the next request body, read
        under the deadlines and limits above, its budget share held until the block ends.
        Raises FrameTooLargeError, TimeoutError or asyncio.IncompleteReadError."""
        return _Frame(self, reader, budget)


class _Frame:
    def __init__(self, conn: Conn, reader: asyncio.StreamReader, budget: ByteBudget) -> None:
        self.conn, self.reader, self.budget = conn, reader, budget
        self._held: contextlib.AbstractAsyncContextManager | None = None

    async def __aenter__(self) -> bytes | bytearray:
        conn, cfg, reader = self.conn, self.conn.cfg, self.reader
        loop = asyncio.get_running_loop()
        size = codec.FRAME_HEADER.size
        if conn.hello:
            try:  # idle between requests
                async with asyncio.timeout(cfg.idle_timeout_s):
                    first = await reader.readexactly(1)
            except TimeoutError:
                raise IdleError from None
            deadline = loop.time() + cfg.read_timeout_s
        else:
            first, deadline = b"", conn.hello_deadline
        async with asyncio.timeout_at(deadline):
            head = first + await reader.readexactly(size - len(first))
        (length,) = codec.FRAME_HEADER.unpack(head)
        if not conn.hello and length > cfg.max_hello_bytes:
            raise FrameTooLargeError(length, cfg.max_hello_bytes, "max_hello_bytes before hello")
        if length > cfg.max_frame_bytes:
            raise FrameTooLargeError(length, cfg.max_frame_bytes, "max_frame_bytes")
        if length > cfg.max_hello_bytes:
            self._held = self.budget.hold(length, conn.client)
            await self._held.__aenter__()
            deadline = loop.time() + cfg.read_timeout_s
        try:
            async with asyncio.timeout_at(deadline):
                return await read_body(reader, length)
        except BaseException:
            await self.__aexit__(None, None, None)
            raise

    async def __aexit__(self, *exc: object) -> None:
        if self._held is not None:
            held, self._held = self._held, None
            await held.__aexit__(None, None, None)


async def read_body(reader: asyncio.StreamReader, n: int) -> bytes | bytearray:
    """Exactly `n` bytes; large bodies go into one buffer of size `n` (readexactly would
    grow its own buffer to `n` and then copy it)."""
    if n <= CHUNK:
        return await reader.readexactly(n)
    buf = bytearray(n)
    got = 0
    with memoryview(buf) as view:
        while got < n:
            chunk = await reader.read(min(n - got, CHUNK))
            if not chunk:
                raise asyncio.IncompleteReadError(b"", n)
            view[got : got + len(chunk)] = chunk
            got += len(chunk)
    return buf


async def write_frame(writer: asyncio.StreamWriter, parts: list, timeout: float) -> None:
    """Write one frame of `parts` (buffers, not copied here) within `timeout` seconds, in
    pieces of at most `WRITE_CHUNK` bytes (small parts are joined into a piece, large ones
    sliced), each handed to the transport once the previous one was taken; the transport
    therefore never buffers more than about one piece. When the deadline passes the
    transport is aborted (its buffers freed) and TimeoutError raised."""
    views = [memoryview(p).cast("B") for p in parts]
    size = sum(v.nbytes for v in views)
    try:
        async with asyncio.timeout(timeout):
            piece: list = [codec.FRAME_HEADER.pack(size)]
            filled = len(piece[0])
            for view in views:
                for off in range(0, view.nbytes, WRITE_CHUNK):
                    part = view[off : off + WRITE_CHUNK]
                    if filled + part.nbytes > WRITE_CHUNK:
                        await _put(writer, piece)
                        piece, filled = [], 0
                    piece.append(part)
                    filled += part.nbytes
            await _put(writer, piece)
    except BaseException:
        abort(writer)
        raise


def abort(writer: asyncio.StreamWriter) -> None:
    """Drop the connection now: the transport's buffers and (by a reset, SO_LINGER 0) the
    kernel's send buffer too, instead of flushing them to a client that does not read."""
    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    writer.transport.abort()


async def _put(writer: asyncio.StreamWriter, piece: list) -> None:
    writer.write(piece[0] if len(piece) == 1 else b"".join(piece))
    await writer.drain()


class Admission:
    """Which connections are open: those without a hello (oldest first) and the
    authenticated ones per client (see the limits above)."""

    def __init__(self, cfg: BufferConfig) -> None:
        self.cfg = cfg
        self.conns: set[asyncio.Task] = set()
        self.unauth: dict[asyncio.Task, None] = {}  # no hello yet, oldest first
        self.per_client: dict[str, int] = {}

    def admit(self, task: asyncio.Task) -> tuple[bool, bool]:
        """(admitted, evicted): room for one more connection? When full, the oldest
        connection that has not completed its hello is closed to make room; without one the
        new one is refused."""
        cfg, evicted = self.cfg, False
        full = len(self.conns) >= cfg.max_connections or len(self.unauth) >= cfg.max_unauthenticated
        if full:
            if not self.unauth:
                return False, False
            oldest = next(iter(self.unauth))
            del self.unauth[oldest]
            oldest.cancel()
            evicted = True
        self.conns.add(task)
        self.unauth[task] = None
        return True, evicted

    def authenticate(self, conn: Conn, client: str) -> None:
        """Count `conn` as `client`'s; RequestError ``too_many_connections`` beyond the limit."""
        if conn.hello:  # a second hello on the connection: counted once, as its new client
            self._uncount(conn.client)
            conn.hello = False
        held = self.per_client.get(client, 0)
        if held >= self.cfg.max_connections_per_client:
            raise RequestError(
                "too_many_connections",
                f"client {client!r} already holds {held} connections "
                f"(max_connections_per_client={self.cfg.max_connections_per_client})",
            )
        self.per_client[client] = held + 1
        conn.client, conn.hello = client, True
        self.unauth.pop(conn.task, None)

    def leave(self, conn: Conn) -> None:
        self.conns.discard(conn.task)
        self.unauth.pop(conn.task, None)
        if conn.hello:
            self._uncount(conn.client)

    def _uncount(self, client: str) -> None:
        left = self.per_client[client] - 1
        if left:
            self.per_client[client] = left
        else:
            del self.per_client[client]
