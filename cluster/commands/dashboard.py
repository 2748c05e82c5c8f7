"""`credit dashboard`: serve the live dashboard on 127.0.0.1 and print its URL.

Source, in order: `--prometheus URL`; else `--targets`/`--sd-file` (scrape the exporters
directly); else the Prometheus that `credit metrics up` started, if it runs; else the
exporters of every live run on this machine (the file-SD links in ~/.credit/metrics/runs/).
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
from pathlib import Path

from cluster.commands import add_command
from cluster.config.schema import ConfigError, build
from cluster.dashboard.server import (
    DashboardConfig,
    DashboardServer,
    ExporterSource,
    PrometheusSource,
    Source,
)
from cluster.metrics.discovery import parse_target, read_file_sd, read_runs_sd, runs_sd_dir
from cluster.metrics.prometheus import running_url

# ConfigError (not cluster.cli.UsageError, which would be a circular import) -> exit code 2.

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "dashboard",
        "Serve the live metrics dashboard on 127.0.0.1 and print its URL; writes nothing.",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument("--prometheus", metavar="URL", help="read this Prometheus (HTTP API)")
    src.add_argument("--targets", metavar="HOST:PORT,...", help="scrape these exporters")
    src.add_argument("--sd-file", metavar="PATH", help="scrape the exporters of this file_sd JSON")
    p.add_argument("--port", type=int, default=8050, help="HTTP port (0 = a free one)")
    p.add_argument("--range", type=float, default=300.0, help="seconds shown (default 300)")
    p.add_argument("--state-dir", default="", help="where `credit metrics up` keeps its state")
    p.set_defaults(func=cmd_dashboard)


def _static_targets(text: str) -> list[str]:
    out = []
    for item in text.split(","):
        if item.strip():
            try:
                host, port = parse_target(item)
            except ValueError as e:
                raise ConfigError(f"--targets: {e}") from None
            out.append(f"{host}:{port}")
    if not out:
        raise ConfigError("--targets: give at least one host:port")
    return out


def _sd_targets(path: Path) -> list[str]:
    return [f"{h}:{p}" for h, p in read_file_sd(path)]


def _runs_targets() -> list[str]:
    return [f"{h}:{p}" for h, p in read_runs_sd()]  # re-read at every scrape


def _run_dir(path: Path) -> Path | None:
    """The run folder a run's own targets.json names (its "run" label), if any."""
    groups = json.loads(path.read_text())
    runs = {g.get("labels", {}).get("run") for g in groups if isinstance(g, dict)} - {None}
    return Path(runs.pop()) if len(runs) == 1 else None


def choose_source(args: argparse.Namespace, cfg: DashboardConfig) -> Source:
    """Pick where the charts read from (see the module docstring for the order)."""
    if args.prometheus:
        if not args.prometheus.startswith(("http://", "https://")):
            raise ConfigError(f"--prometheus must be an http(s) URL, got {args.prometheus!r}")
        return PrometheusSource(args.prometheus, cfg)
    if args.targets:
        targets = _static_targets(args.targets)
        return ExporterSource(lambda: targets, cfg)
    if args.sd_file:
        path = Path(args.sd_file).expanduser()
        if not path.is_file():
            raise ConfigError(f"--sd-file: {path} does not exist")
        _sd_targets(path)  # fail now, not in the scrape thread, if it is not file_sd JSON
        return ExporterSource(
            functools.partial(_sd_targets, path), cfg, label=str(path), run_dir=_run_dir(path)
        )
    url = running_url(args.state_dir)
    if url:
        return PrometheusSource(url, cfg)
    folder = runs_sd_dir()
    log.info("no Prometheus running; scraping the exporters of every live run (%s)", folder)
    return ExporterSource(_runs_targets, cfg, label=f"every live run ({folder})")


def cmd_dashboard(args: argparse.Namespace) -> int:
    cfg = build(DashboardConfig, {"port": args.port, "range_s": args.range})
    try:
        source = choose_source(args, cfg)
    except ConfigError:
        raise
    except ValueError as e:  # a broken file-SD file
        raise ConfigError(str(e)) from None
    try:
        server = DashboardServer(cfg, source)
    except OSError as e:
        raise ConfigError(f"cannot listen on {cfg.host}:{cfg.port}: {e.strerror}") from None
    print(f"credit dashboard: {server.url}  (source: {source.describe()})", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
    return 0
