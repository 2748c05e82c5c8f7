"""Prometheus metrics of one buffer server (docs/design.md, "Metrics"), on their own registry.

A dedicated CollectorRegistry per server keeps several servers in one process (tests)
from colliding; `start_exporter` serves it on 127.0.0.1 only.
"""

from __future__ import annotations

import logging

from prometheus_client import CollectorRegistry, Counter, Gauge, start_http_server

log = logging.getLogger(__name__)


class BufferMetrics:
    """Counters and gauges the server updates per request (never per step).

    Args:
        table_names: tables to pre-create label children for, so they export zeros.
    """

    def __init__(self, table_names: list[str]) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.inserts = Counter(
            "credit_buffer_inserts",
            "Episodes stored, per table (duplicates excluded).",
            ["table"],
            registry=self.registry,
        )
        self.samples = Counter(
            "credit_buffer_samples",
            "Episodes handed out by sample requests, per table.",
            ["table"],
            registry=self.registry,
        )
        self.size = Gauge(
            "credit_buffer_size_episodes",
            "Episodes currently held, per table.",
            ["table"],
            registry=self.registry,
        )
        self.rejected = Counter(
            "credit_buffer_rejected",
            "Requests or episodes refused, by reason (error code or 'duplicate').",
            ["reason"],
            registry=self.registry,
        )
        for name in table_names:
            self.inserts.labels(table=name)
            self.samples.labels(table=name)
            self.size.labels(table=name).set(0)
        self._server = None

    def start_exporter(self, port: int) -> int:
        """Serve /metrics on 127.0.0.1:`port` (0 = any free port); return the bound port."""
        server, _thread = start_http_server(port, addr="127.0.0.1", registry=self.registry)
        self._server = server
        bound = int(server.server_address[1])
        log.info("buffer metrics on http://127.0.0.1:%d/metrics", bound)
        return bound

    def stop_exporter(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None
