"""When the buffer service snapshots (`SnapshotScheduling`, a part of `server.BufferServer`):
after ``snapshot_every_inserts`` logged inserts or once the log holds
``snapshot_every_bytes``, on the snapshot op, and on shutdown; one at a time, started on the
event loop and written in a thread. A snapshot that cannot be started or written (a full
disk) is skipped and tried again later: the logs still hold everything."""

from __future__ import annotations

import asyncio
import logging

from buffer_service.requests import RequestError
from buffer_service.storage import WriteError

log = logging.getLogger("buffer_service.server")


class SnapshotScheduling:
    """Snapshot scheduling of `BufferServer` (uses its cfg, storage, state and _server)."""

    _snapshotting: asyncio.Future | None
    close_error: str | None

    async def _final_snapshot(self) -> None:
        try:
            await self._snapshot()
        except RequestError as e:  # a full disk: nothing is lost, the logs hold it all
            self.close_error = f"{e.code}: {e}"
            log.error(
                "final snapshot not written (%s); the logs hold every acknowledged episode "
                "and a restart replays them",
                self.close_error,
            )

    def _maybe_snapshot(self) -> None:
        """Start a snapshot in the background when enough inserts were logged since the last."""
        every, st = self.cfg.snapshot_every_inserts, self.storage
        if st is None or self._snapshotting is not None:
            return
        by_bytes = self.cfg.snapshot_every_bytes and st.size >= self.cfg.snapshot_every_bytes
        if (every and st.records_since_snapshot >= every) or by_bytes:
            try:
                self._start_snapshot()
            except WriteError as e:  # a full disk: the log goes on; tried again later
                log.warning("snapshot not started: %s", e)

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
        except WriteError as e:
            raise RequestError(e.code, f"snapshot failed: {e}") from None
        except OSError as e:
            code = WriteError("", e).code
            raise RequestError(code, f"snapshot failed: {e}") from None
