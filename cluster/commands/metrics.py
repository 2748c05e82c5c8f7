"""`credit metrics up|down|status`: a local Prometheus that scrapes the running cluster."""

from __future__ import annotations

import argparse

from cluster.commands import add_command
from cluster.config.schema import build
from cluster.metrics import prometheus as prom


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "metrics",
        "Run a local Prometheus that scrapes every live credit run on this machine; its "
        "config, log and samples live in ~/.credit/metrics/.",
    )
    msub = p.add_subparsers(dest="metrics_command", required=True, metavar="METRICS_COMMAND")
    state_help = "where the pid file, generated config and log live (default ~/.credit/metrics)"

    up = add_command(
        msub,
        "up",
        "Start Prometheus on 127.0.0.1, detached; writes prometheus.yml, prometheus.json "
        "(pid, URL), its log and its samples (data/) in the state folder.",
    )
    up.add_argument(
        "--sd-file",
        default="",
        help="a file_sd JSON file (or a glob of them) to scrape instead of every live run "
        "(default: each cluster run's OUT/targets.json, linked in ~/.credit/metrics/runs/)",
    )
    up.add_argument("--port", type=int, default=9090, help="HTTP port; 0 picks a free one")
    up.add_argument("--data-dir", default="", help="TSDB folder (default <state-dir>/data)")
    up.add_argument("--state-dir", default="", help=state_help)
    up.add_argument(
        "--scrape-interval", type=float, default=1.0, help="seconds between scrapes (default 1)"
    )
    up.add_argument("--retention", default="1d", help="how long samples are kept (default 1d)")
    up.set_defaults(func=cmd_up)

    down = add_command(
        msub,
        "down",
        "Stop the Prometheus that `up` started and remove its prometheus.json; the samples stay.",
    )
    down.add_argument("--state-dir", default="", help=state_help)
    down.set_defaults(func=cmd_down)

    status = add_command(
        msub,
        "status",
        "Print the running Prometheus's URL (exit code 1 if none runs); writes nothing.",
    )
    status.add_argument("--state-dir", default="", help=state_help)
    status.set_defaults(func=cmd_status)


def cmd_up(args: argparse.Namespace) -> int:
    cfg = build(
        prom.PrometheusConfig,
        {
            "sd_file": args.sd_file,
            "port": args.port,
            "data_dir": args.data_dir,
            "state_dir": args.state_dir,
            "scrape_interval_s": args.scrape_interval,
            "retention": args.retention,
        },
    )
    state = prom.start(cfg)
    sd = cfg.resolved().sd_file
    what = f"every live run ({sd})" if not args.sd_file else sd
    print(f"prometheus ready at {state.url} (pid {state.pid}); scraping {what}")
    print(f"log: {state.log_file}; stop with: credit metrics down")
    return 0


def cmd_down(args: argparse.Namespace) -> int:
    state = prom.stop(args.state_dir)
    if state is None:
        print("no prometheus recorded; nothing to stop")
    else:
        print(f"stopped prometheus (pid {state.pid}, {state.url})")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    url = prom.running_url(args.state_dir)
    print(url if url else "not running")
    return 0 if url else 1
