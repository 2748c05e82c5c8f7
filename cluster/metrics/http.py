"""The HTTP endpoint of an exporter's registry (`serve`, `stop`), on 127.0.0.1 by default."""

from __future__ import annotations

import logging
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    generate_latest,
)

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"


class QuietHTTPServer(ThreadingHTTPServer):
    """A threading HTTP server for which a client that hangs up before the reply is no error.

    The dashboard gives up on a scrape after 2 s and a browser drops a poll when its page
    reloads; a busy process then answers into a closed socket. socketserver would print a
    BrokenPipeError traceback for each; this logs one debug line instead.
    """

    def handle_error(self, request: object, client_address: tuple) -> None:
        if isinstance(sys.exc_info()[1], (BrokenPipeError, ConnectionResetError)):
            log.debug("http %s:%s hung up before the reply", *client_address[:2])
            return
        super().handle_error(request, client_address)


class _Handler(BaseHTTPRequestHandler):
    registry: CollectorRegistry  # set on the per-server subclass

    def do_GET(self) -> None:
        if self.path.split("?")[0] not in ("/", "/metrics"):
            self.send_error(404, "only /metrics is served")
            return
        body = generate_latest(self.registry)
        self.send_response(200)
        self.send_header("Content-Type", CONTENT_TYPE_LATEST)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: object) -> None:
        log.debug("exporter %s: " + format, self.address_string(), *args)


_SERVERS: dict[tuple[str, int], ThreadingHTTPServer] = {}
_SERVERS_LOCK = threading.Lock()


def serve(registry: CollectorRegistry, port: int = 0, host: str = DEFAULT_HOST) -> tuple[str, int]:
    """Serve `registry` at http://host:port/metrics from a daemon thread.

    Args:
        registry: what to expose.
        port: TCP port; 0 picks a free one.
        host: address to bind; loopback by default. Bind a routable address only on a
            multi-node cluster whose Prometheus scrapes over the network.

    Returns:
        (host, port) actually bound; pass it to `stop` to close the exporter.
    """
    if not 0 <= port <= 65535:
        raise ValueError(f"port must be in 0..65535, got {port}")
    handler = type("MetricsHandler", (_Handler,), {"registry": registry})
    server = QuietHTTPServer((host, port), handler)
    server.daemon_threads = True
    bound = (host, int(server.server_address[1]))
    thread = threading.Thread(target=server.serve_forever, name=f"metrics-{bound[1]}", daemon=True)
    thread.start()
    with _SERVERS_LOCK:
        _SERVERS[bound] = server
    log.info("metrics exporter on http://%s:%d/metrics", *bound)
    return bound


def stop(endpoint: tuple[str, int]) -> None:
    """Close an exporter that `serve` started in this process (no-op when unknown)."""
    with _SERVERS_LOCK:
        server = _SERVERS.pop(tuple(endpoint), None)  # type: ignore[arg-type]
    if server is not None:
        server.shutdown()
        server.server_close()
