"""The live dashboard's HTTP server: one static page plus `/api/panels` (JSON series).

The page (`static/`) only draws. The series come from one of two sources:

* `PrometheusSource`: every panel query runs as a PromQL `query_range` against a running
  Prometheus (the server proxies it, so the browser needs no access to Prometheus);
* `ExporterSource`: a background thread scrapes the exporters directly every second and
  `cluster.dashboard.local` computes the same series from a short in-memory history.

    server = DashboardServer(cfg, source)       # binds 127.0.0.1
    server.start(); print(server.url); ...; server.close()
"""

from __future__ import annotations

import json
import logging
import threading
import time
import urllib.parse
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler
from pathlib import Path
from typing import Any, Protocol

from cluster.config.schema import ConfigError
from cluster.dashboard import local
from cluster.dashboard.panels import PANELS, RUN_INFO, Panel
from cluster.metrics.http import QuietHTTPServer
from cluster.metrics.prometheus import query_range

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parent / "static"
_NOT_FINITE = ("NaN", "+Inf", "-Inf")
STATIC_TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css"}


@dataclass(frozen=True)
class DashboardConfig:
    """Settings of `credit dashboard`.

    Attributes:
        host: address to bind (loopback).
        port: HTTP port; 0 picks a free one.
        range_s: how many seconds of history the charts show.
        rate_window_s: window of the per-second rates (PromQL rate()[window]).
        scrape_interval_s: exporter mode: seconds between scrapes.
        history_s: exporter mode: seconds of snapshots kept in memory (>= range_s).
        refresh_s: how often the page asks for new data.
    """

    host: str = "127.0.0.1"
    port: int = 8050
    range_s: float = 300.0
    rate_window_s: float = 15.0
    scrape_interval_s: float = 1.0
    history_s: float = 900.0
    refresh_s: float = 2.0

    def validate(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ConfigError(f"dashboard port must be in 0..65535, got {self.port}")
        if self.range_s <= 0 or self.history_s < self.range_s:
            raise ConfigError("need 0 < range_s <= history_s")
        if self.rate_window_s < 2 * self.scrape_interval_s:
            raise ConfigError("rate_window_s must cover at least two scrapes")
        if self.scrape_interval_s <= 0 or self.refresh_s <= 0:
            raise ConfigError("scrape_interval_s and refresh_s must be > 0")


Series = list[dict[str, Any]]  # [{"name": str, "points": [[t, v], ...]}]


class Source(Protocol):
    """Where panel series come from."""

    def describe(self) -> str: ...

    def series(self, panel: Panel, start: float, end: float) -> tuple[Series, list[str]]: ...

    def run(self, start: float, end: float) -> dict[str, Any]:
        """{"algos": [the run's algorithms], "ended": None or `ended_run`'s dict}."""
        ...


def ended_run(run_dir: Path | None, last_seen: float) -> dict[str, Any]:
    """A run whose exporters all stopped answering: "finished" with its summary.json's
    final numbers when it wrote one (its clean end), else "stopped" (killed or crashed)."""
    path = run_dir / "summary.json" if run_dir is not None else None
    if path is None or not path.is_file():
        return {"state": "stopped", "last_seen": last_seen}
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError):
        return {"state": "stopped", "last_seen": last_seen}
    keys = ("algo", "env", "t_env", "wall_s", "final_test_return_mean", "final_test_won_mean")
    return {
        "state": "finished",
        "last_seen": last_seen,
        "finished_at": path.stat().st_mtime,
        "summary": {k: summary.get(k) for k in keys},
    }


class PrometheusSource:
    """Panel series from PromQL range queries against `url`."""

    def __init__(self, url: str, cfg: DashboardConfig) -> None:
        self.url = url.rstrip("/")
        self.cfg = cfg

    def describe(self) -> str:
        return f"Prometheus at {self.url}"

    def series(self, panel: Panel, start: float, end: float) -> tuple[Series, list[str]]:
        step = max(1.0, (end - start) / 300)
        window = f"{int(self.cfg.rate_window_s)}s"
        out: Series = []
        errors: list[str] = []
        for q in panel.queries:
            try:
                result = query_range(self.url, q.promql(window), start, end, step)
            except (OSError, ValueError) as e:
                errors.append(f"{panel.id}: {e}")
                continue
            for r in result:
                values = r["values"]
                points = [[float(t), float(v)] for t, v in values if v not in _NOT_FINITE]
                if points:
                    out.append({"name": q.name_for(r["metric"]), "points": points})
        return out, errors

    def run(self, start: float, end: float) -> dict[str, Any]:
        try:
            result = query_range(self.url, RUN_INFO, start, end, max(1.0, (end - start) / 30))
        except (OSError, ValueError):
            result = []
        return {
            "algos": sorted({r["metric"].get("algo", "") for r in result} - {""}),
            "ended": None,
        }


class ExporterSource:
    """Panel series computed from direct scrapes of the exporters.

    Args:
        targets: returns the current "host:port" list.
        label: where the targets come from (shown on the page), e.g. the file-SD path.
        cfg: the dashboard settings (scrape interval, history, rate window).
        fetcher: target -> exposition text (default: HTTP GET /metrics).
        run_dir: the run's folder (its summary.json tells a finished run from a stopped one
            once no exporter answers).
    """

    def __init__(
        self,
        targets: Callable[[], Sequence[str]],
        cfg: DashboardConfig,
        fetcher: Callable[[str], str] = local.fetch,
        label: str = "",
        run_dir: Path | None = None,
    ) -> None:
        self.cfg = cfg
        self.label = label
        self.run_dir = run_dir
        self.history = local.ScrapeHistory(targets, cfg.history_s, fetcher)
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self.history.run, args=(cfg.scrape_interval_s, self._stop), daemon=True
        )

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)

    def describe(self) -> str:
        targets = self.history.last_targets
        where = f" listed in {self.label}" if self.label else ""
        return f"{len(targets)} exporter(s){where}, scraped directly" + (
            "" if targets else " (none listed yet)"
        )

    def series(self, panel: Panel, start: float, end: float) -> tuple[Series, list[str]]:
        snaps = [s for s in self.history.snapshots() if s.t <= end]
        out: Series = []
        for q in panel.queries:
            found = local.evaluate(q, snaps, self.cfg.rate_window_s, since=start)
            for name, points in sorted(found.items()):
                out.append({"name": name, "points": [[t, v] for t, v in points]})
        errors = [f"{t}: {e}" for t, e in sorted(self.history.errors.items())]
        return out, errors

    def run(self, start: float, end: float) -> dict[str, Any]:
        snaps = self.history.snapshots()
        algos = set()
        for snap in reversed(snaps):
            algos = {dict(k[1]).get("algo", "") for k in snap.samples if k[0] == RUN_INFO}
            if algos:
                break
        h = self.history
        down = bool(snaps) and bool(h.last_targets) and set(h.errors) >= set(h.last_targets)
        ended = ended_run(self.run_dir, snaps[-1].t) if down else None
        return {"algos": sorted(algos - {""}), "ended": ended}


def panels_payload(source: Source, range_s: float, now: float | None = None) -> dict[str, Any]:
    """The JSON the page draws: the panels of the run's algorithm with their series over the
    last `range_s` seconds (up to the run's last scrape once it has ended, whose end then
    replaces the exporters' connection errors)."""
    end = time.time() if now is None else now
    run = source.run(end - range_s, end)
    if run["ended"] is not None:
        end = min(end, run["ended"]["last_seen"] + 1.0)
    start = end - range_s
    panels, errors = [], []
    for panel in (p for p in PANELS if p.shown_for(set(run["algos"]))):
        series, errs = source.series(panel, start, end)
        errors.extend(errs)
        panels.append(
            {
                "id": panel.id,
                "title": panel.title,
                "unit": panel.unit,
                "description": panel.description,
                "y_min": panel.y_min,
                "y_max": panel.y_max,
                "series": series,
            }
        )
    return {
        "source": source.describe(),
        "start": start,
        "end": end,
        "panels": panels,
        "run": run,
        "errors": [] if run["ended"] is not None else sorted(set(errors))[:20],
    }


class _Handler(BaseHTTPRequestHandler):
    source: Source
    cfg: DashboardConfig

    def do_GET(self) -> None:
        url = urllib.parse.urlsplit(self.path)
        if url.path == "/api/panels":
            params = urllib.parse.parse_qs(url.query)
            try:
                range_s = float(params.get("range", [self.cfg.range_s])[0])
            except ValueError:
                self._send(400, b"range must be a number of seconds", "text/plain")
                return
            range_s = min(max(range_s, 10.0), self.cfg.history_s)
            body = json.dumps(panels_payload(self.source, range_s)).encode()
            self._send(200, body, "application/json")
        elif url.path == "/api/config":
            body = json.dumps({"refresh_s": self.cfg.refresh_s, "range_s": self.cfg.range_s})
            self._send(200, body.encode(), "application/json")
        elif url.path in ("/", "/index.html"):
            self._static("index.html")
        elif url.path.startswith("/static/"):
            self._static(url.path.removeprefix("/static/"))
        else:
            self._send(404, b"not found", "text/plain")

    def _static(self, name: str) -> None:
        path = STATIC_DIR / name
        # Only plain files directly in static/ with a known type: no path traversal.
        if "/" in name or path.suffix not in STATIC_TYPES or not path.is_file():
            self._send(404, b"not found", "text/plain")
            return
        self._send(200, path.read_bytes(), STATIC_TYPES[path.suffix] + "; charset=utf-8")

    def _send(self, code: int, body: bytes, ctype: str) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: object) -> None:
        log.debug("dashboard %s: " + format, self.address_string(), *args)


class DashboardServer:
    """Serves the page and `/api/panels` from `source` on cfg.host:cfg.port."""

    def __init__(self, cfg: DashboardConfig, source: Source) -> None:
        cfg.validate()
        handler = type("DashboardHandler", (_Handler,), {"source": source, "cfg": cfg})
        self.httpd = QuietHTTPServer((cfg.host, cfg.port), handler)
        self.httpd.daemon_threads = True
        self.source = source
        self.url = f"http://{cfg.host}:{self.httpd.server_address[1]}/"
        self._thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    def start(self) -> DashboardServer:
        if isinstance(self.source, ExporterSource):
            self.source.start()
        self._thread.start()
        return self

    def serve_forever(self) -> None:
        """Block serving until interrupted (the CLI's foreground mode)."""
        if isinstance(self.source, ExporterSource):
            self.source.start()
        self.httpd.serve_forever()

    def close(self) -> None:
        if self._thread.is_alive():  # shutdown() would wait forever if nothing serves
            self.httpd.shutdown()
        self.httpd.server_close()
        if isinstance(self.source, ExporterSource):
            self.source.close()
