"""Running a `BufferServer`: in a daemon thread of this process (`ServerThread`,
`start_server_thread`: tests, embedding) or as the process itself (`run`: `credit buffer
serve`)."""

from __future__ import annotations

import asyncio
import logging
import os
import threading

from buffer_service.config import BufferConfig
from buffer_service.packed import warm_kernels
from buffer_service.server import BufferServer

log = logging.getLogger(__name__)


class ServerThread:
    """A `BufferServer` on its own event loop in a daemon thread (tests, embedding).

    Args:
        cfg: the server config.

    Attributes:
        host, port: where it listens once `start` returned; metrics_port likewise.
    """

    def __init__(self, cfg: BufferConfig) -> None:
        self.server = BufferServer(cfg)
        self.host = cfg.host
        self.port = 0
        self.metrics_port: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="buffer-server", daemon=True)

    def start(self, timeout: float = 30.0) -> ServerThread:
        self._thread.start()
        if not self._ready.wait(timeout):
            raise TimeoutError("buffer server did not start")
        if self._error is not None:
            raise self._error
        return self

    def _run(self) -> None:
        asyncio.run(self._main())

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        try:
            await self.server.start()
        except BaseException as e:
            self._error = e
            self._ready.set()
            return
        self.port, self.metrics_port = self.server.port, self.server.metrics_port
        self._ready.set()
        await self._stop.wait()
        await self.server.close(snapshot=self._snapshot_on_stop)

    def stop(self, snapshot: bool = True, timeout: float = 30.0) -> None:
        """Close the server (final snapshot unless `snapshot` is False) and join the thread."""
        self._snapshot_on_stop = snapshot
        if self._loop is not None and self._stop is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout)

    _snapshot_on_stop = True

    def __enter__(self) -> ServerThread:
        return self.start() if not self._thread.is_alive() else self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start_server_thread(cfg: BufferConfig) -> ServerThread:
    """Start a buffer server in a background thread; returns once it listens.

    Args:
        cfg: the server config (port 0 picks a free port; read it from ``.port``).

    Returns:
        The running `ServerThread`; call ``.stop()`` to shut it down.
    """
    return ServerThread(cfg).start()


def run(cfg: BufferConfig, port_file: str | None = None) -> str | None:
    """Serve in the foreground until SIGINT/SIGTERM (the `credit buffer serve` body).

    Args:
        cfg: the server config.
        port_file: once listening, atomically write ``{"host", "port", "metrics_port",
            "pid"}`` as JSON here (how a launcher learns a port picked with port 0).

    Returns:
        None after a clean shutdown, else why the final snapshot was not written (a full
        disk; the logs still hold every acknowledged episode).
    """
    return asyncio.run(_run_main(cfg, port_file))


async def _run_main(cfg: BufferConfig, port_file: str | None) -> str | None:
    import json
    import signal

    warm_kernels()  # before it listens, so that the first insert does not wait for numba
    server = BufferServer(cfg)
    await server.start()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if port_file:
        info = {"host": cfg.host, "port": server.port, "metrics_port": server.metrics_port}
        info["pid"] = os.getpid()
        tmp = f"{port_file}.tmp"
        with os.fdopen(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), "w") as f:
            json.dump(info, f)
        os.replace(tmp, port_file)
    try:
        await stop.wait()
    finally:
        log.info("buffer service shutting down")
        await server.close()
    return server.close_error
