"""Reading request frames under deadlines and limits, so that no client can starve others.

* A connection that has not completed its hello must do so within ``hello_timeout_s`` of
  connecting and may send frames of at most ``max_hello_bytes``; at most
  ``max_unauthenticated`` such connections exist, a new one closing the oldest.
* An authenticated connection may idle between frames, but once a frame's first byte has
  arrived the rest of it must arrive within ``read_timeout_s``.
* Bodies above ``max_hello_bytes`` hold a share of ``max_inflight_bytes`` while they are
  read and handled (further ones wait), and are read into one buffer of exactly their size.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

from buffer_service import codec
from buffer_service.config import BufferConfig

CHUNK = 1 << 20  # bodies above this are read piecewise into a buffer of their own size


class FrameTooLargeError(Exception):
    def __init__(self, length: int, limit: int, field: str) -> None:
        super().__init__(f"frame of {length} bytes exceeds {field}={limit}")


class ByteBudget:
    """Bytes of large request bodies held at once, over all connections."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.used = 0
        self._freed = asyncio.Condition()

    @contextlib.asynccontextmanager
    async def hold(self, n: int) -> AsyncIterator[None]:
        async with self._freed:
            await self._freed.wait_for(lambda: self.used + n <= self.limit)
            self.used += n
        try:
            yield
        finally:
            async with self._freed:
                self.used -= n
                self._freed.notify_all()


class Conn:
    """One client connection: whether it said hello, and by when it must."""

    def __init__(self, task: asyncio.Task | None, cfg: BufferConfig) -> None:
        self.task = task
        self.cfg = cfg
        self.hello = False
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
            first = await reader.readexactly(1)  # idle between requests: no deadline
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
            self._held = self.budget.hold(length)
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
