"""The buffer service as a supervised child process of the launcher.

Started with `credit buffer serve` on 127.0.0.1, a private token and a snapshot folder; if it
dies (kill -9 included) `ensure_running` starts it again on the same port and folder, and it
restores every acknowledged episode from its snapshot and log. The child gets SIGKILL when
the launcher dies (Linux PR_SET_PDEATHSIG), so a killed learner leaves no orphan service.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import os
import secrets
import signal
import subprocess
import sys
import time
from pathlib import Path

from buffer_service.config import TableConfig
from buffer_service.episode import EpisodeSchema

log = logging.getLogger(__name__)


def _die_with_parent() -> None:  # runs in the child between fork and exec
    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def table_arg(t: TableConfig) -> str:
    """A TableConfig as `credit buffer serve --table` key=value pairs."""
    r = t.rate_limiter
    return (
        f"name={t.name},kind={t.kind},capacity={t.capacity},max_times_sampled={t.max_times_sampled},"
        f"max_bytes={t.max_bytes},"
        f"replacement={str(t.replacement).lower()},"
        f"min_size_to_sample={r.min_size_to_sample},samples_per_insert={r.samples_per_insert},"
        f"error_buffer={r.error_buffer}"
    )


class BufferProcess:
    """One `credit buffer serve` child.

    Calling loop::

        proc = BufferProcess(tables, schema, Path(out) / "buffer")
        proc.start()                          # returns once it listens; proc.port, proc.token
        ...
        proc.ensure_running()                 # restart after a crash (same port and folder)
        proc.stop()
    """

    def __init__(
        self,
        tables: tuple[TableConfig, ...],
        schema: EpisodeSchema,
        folder: Path,
        fsync: bool = True,
        metrics: bool = True,
        token: str | None = None,
        host: str = "127.0.0.1",
        seed: int | None = None,
        repair: bool = False,
        store_state: bool = True,
    ):
        self.tables, self.schema, self.folder = tables, schema, Path(folder)
        self.store_state = store_state
        self.seed, self.repair = seed, repair
        self.fsync, self.metrics = fsync, metrics
        self.token = token or secrets.token_hex(16)
        self.host = host
        self.port = 0
        self.metrics_port: int | None = None
        self.proc: subprocess.Popen | None = None
        self.restarts = 0

    def _command(self, port_file: Path) -> list[str]:
        schema = ",".join(f"{k}={v}" for k, v in self.schema.to_dict().items())
        cmd = [sys.executable, "-m", "cluster.cli", "buffer", "serve", "--host", self.host]
        cmd += ["--port", str(self.port), "--port-file", str(port_file), "--schema", schema]
        cmd += ["--snapshot-dir", str(self.folder / "data")]
        for t in self.tables:
            cmd += ["--table", table_arg(t)]
        if not self.fsync:
            cmd.append("--no-fsync")
        if self.seed is not None:
            cmd += ["--seed", str(self.seed)]
        if self.repair:
            cmd.append("--repair")
        if not self.store_state:
            cmd.append("--no-state")
        if self.metrics:
            cmd += ["--metrics-port", str(self.metrics_port or 0)]
        return cmd

    def start(self, timeout_s: float = 60.0) -> None:
        """Start the child and wait until it listens (its port file appears)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        port_file = self.folder / "port.json"
        port_file.unlink(missing_ok=True)
        env = {**os.environ, "CREDIT_BUFFER_TOKEN": self.token}
        log_fd = os.open(self.folder / "service.log", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        log_file = os.fdopen(log_fd, "a")  # the child owns it
        self.proc = subprocess.Popen(
            self._command(port_file),
            env=env,
            stdout=log_file,
            stderr=log_file,
            preexec_fn=_die_with_parent,
        )
        log_file.close()
        deadline = time.monotonic() + timeout_s
        while not port_file.exists():
            if self.proc.poll() is not None:
                tail = (self.folder / "service.log").read_text()[-2000:]
                raise RuntimeError(
                    f"the buffer service exited with {self.proc.returncode}:\n{tail}"
                )
            if time.monotonic() > deadline:
                self.proc.kill()
                raise RuntimeError(f"the buffer service did not start within {timeout_s:.0f} s")
            time.sleep(0.05)
        info = json.loads(port_file.read_text())
        self.port, self.metrics_port = int(info["port"]), info.get("metrics_port")
        log.info("buffer service pid %d on %s:%d", self.proc.pid, self.host, self.port)

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc else None

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def ensure_running(self) -> bool:
        """Restart the child if it died; returns True if it had to."""
        if self.alive():
            return False
        code = self.proc.returncode if self.proc else None
        log.warning("buffer service died (exit %s); restarting on port %d", code, self.port)
        self.restarts += 1
        self.start()
        return True

    def stop(self, timeout_s: float = 30.0) -> None:
        """SIGTERM (the service snapshots and exits), SIGKILL after `timeout_s`."""
        if not self.alive():
            return
        assert self.proc is not None
        self.proc.terminate()
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
