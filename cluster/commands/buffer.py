"""`credit buffer serve`: run the episode buffer service in the foreground;
`credit buffer verify DIR`: check a snapshot folder offline and print what it holds (JSON)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os

from buffer_service.config import BufferConfig, RateLimiterConfig, TableConfig, default_tables
from buffer_service.episode import EpisodeSchema
from cluster.commands import add_command

TABLE_HELP = (
    "a table as key=value pairs, repeatable, e.g. "
    "name=cycling,kind=cycling,capacity=32,max_times_sampled=8,min_size_to_sample=32 or "
    "name=replay,kind=replay,capacity=5000,max_bytes=4294967296,samples_per_insert=4,"
    "error_buffer=64 (max_bytes: the table's byte budget, 0 = none; default: cycling 32/K=8 "
    "and replay 5000 within 4 GiB)"
)
log = logging.getLogger(__name__)
LIMITER_KEYS = {f.name for f in dataclasses.fields(RateLimiterConfig)}
# --flag, BufferConfig field, type, the field's unit per the flag's, help (issue 40's limits)
LIMITS = [
    ("--snapshot-every-mb", "snapshot_every_bytes", float, 2**20,
     "also snapshot once the log holds this many MiB (0 = no byte trigger)"),
    ("--read-timeout", "read_timeout_s", float, 1,
     "seconds to transfer a started request or reply; a client not taking its reply is cut off"),
    ("--idle-timeout", "idle_timeout_s", float, 1,
     "close an authenticated connection idle this many seconds (clients reconnect)"),
    ("--max-connections-per-client", "max_connections_per_client", int, 1,
     "authenticated connections one client id may hold"),
    ("--max-inflight-mb", "max_inflight_bytes", float, 2**20,
     "MiB of large requests and sample replies in flight over all connections"),
    ("--max-inflight-per-client-mb", "max_inflight_bytes_per_client", float, 2**20,
     "the share of --max-inflight-mb one client may hold"),
]  # fmt: skip


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "buffer",
        "Serve the episode buffer over TCP, writing its log and snapshots, or check such a "
        "folder offline and print a report.",
    )
    bsub = p.add_subparsers(dest="buffer_command", required=True, metavar="BUFFER_COMMAND")
    s = add_command(
        bsub,
        "serve",
        "Serve episodes over TCP until SIGINT or SIGTERM; writes its log and snapshots to"
        " --snapshot-dir and, with --port-file, that JSON file.",
    )
    s.add_argument("--host", default="127.0.0.1", help="bind address (non-loopback needs a token)")
    s.add_argument("--port", type=int, default=0, help="TCP port; 0 picks a free one")
    s.add_argument("--port-file", help="write {host, port, metrics_port, pid} JSON once listening")
    s.add_argument(
        "--token",
        default=os.environ.get("CREDIT_BUFFER_TOKEN"),
        help="shared secret checked in hello (default: $CREDIT_BUFFER_TOKEN)",
    )
    s.add_argument("--table", action="append", default=[], metavar="SPEC", help=TABLE_HELP)
    s.add_argument(
        "--schema",
        metavar="SPEC",
        help="n_agents=..,obs_dim=..,state_dim=..,"
        "n_actions=..,max_t=.. (default: learned from the first client)",
    )
    s.add_argument(
        "--snapshot-dir", help="log + snapshot directory (omit: in memory, no durability)"
    )
    s.add_argument("--no-fsync", action="store_true", help="ack inserts after write(), not fsync")
    s.add_argument("--seed", type=int, help="seed of the sampling RNG (default: random)")
    s.add_argument(
        "--no-state",
        action="store_true",
        help="drop each episode's global state on insert (for learners that never read it)",
    )
    s.add_argument(
        "--snapshot-every",
        type=int,
        default=BufferConfig.snapshot_every_inserts,
        help="snapshot after this many logged inserts (0 = on demand/shutdown only)",
    )
    s.add_argument(
        "--max-frame-mb",
        type=float,
        default=BufferConfig.max_frame_bytes / 2**20,
        help="largest request frame in MiB",
    )
    s.add_argument(
        "--sample-timeout",
        type=float,
        default=BufferConfig.sample_timeout_s,
        help="longest rate-limiter wait of a sample, seconds",
    )
    s.add_argument(
        "--insert-timeout",
        type=float,
        default=BufferConfig.insert_timeout_s,
        help="longest rate-limiter wait of an insert, seconds",
    )
    s.add_argument(
        "--max-sample",
        type=int,
        default=BufferConfig.max_sample_episodes,
        help="largest batch_size of one sample request",
    )
    s.add_argument(
        "--repair",
        action="store_true",
        help="start from what a damaged --snapshot-dir still holds, discarding (and naming) "
        "what cannot be read and accepting acknowledged episodes found missing (a log cut "
        "short or deleted), instead of refusing to start",
    )
    for flag, field, kind, scale, text in LIMITS:
        default = getattr(BufferConfig, field) / scale
        s.add_argument(flag, type=kind, default=default, help=f"{text} (default {default:g})")
    s.add_argument("--metrics-port", type=int, help="Prometheus port on 127.0.0.1 (0 = any)")
    s.set_defaults(func=cmd_serve)
    v = add_command(
        bsub,
        "verify",
        "Check a snapshot folder offline and print a JSON report of its tables, episodes "
        "and damaged records; writes nothing.",
    )
    v.add_argument("dir", help="the service's --snapshot-dir")
    v.add_argument(
        "--table",
        action="append",
        default=[],
        metavar="SPEC",
        help="tables to restore into when the files record none (format 1); as for serve",
    )
    v.set_defaults(func=cmd_verify)


def _pairs(spec: str, what: str) -> dict[str, str]:
    out = {}
    for part in spec.split(","):
        key, sep, val = part.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"{what} {spec!r}: expected key=value pairs separated by commas")
        out[key.strip()] = val.strip()
    return out


def parse_table(spec: str) -> TableConfig:
    """TableConfig from ``name=..,kind=..,capacity=..,max_times_sampled=..,<limiter keys>``."""
    d = _pairs(spec, "--table")
    limiter = {k: float(d.pop(k)) for k in list(d) if k in LIMITER_KEYS}
    if "min_size_to_sample" in limiter:
        limiter["min_size_to_sample"] = int(limiter["min_size_to_sample"])
    table: dict = {
        k: (int(v) if k in ("capacity", "max_times_sampled", "max_bytes") else v)
        for k, v in d.items()
    }
    if "replacement" in table:
        flag = str(table["replacement"]).lower()
        if flag not in ("true", "false"):
            raise ValueError(f"--table replacement={table['replacement']}: use true or false")
        table["replacement"] = flag == "true"
    table["rate_limiter"] = RateLimiterConfig(**limiter)
    return TableConfig.from_dict(table)


def build_config(args: argparse.Namespace) -> BufferConfig:
    schema = None
    if args.schema:
        schema = EpisodeSchema.from_dict(
            {k: int(v) for k, v in _pairs(args.schema, "--schema").items()}
        )
    cfg = BufferConfig(
        host=args.host,
        port=args.port,
        token=args.token or None,
        tables=tuple(parse_table(t) for t in args.table) or default_tables(),
        schema=schema,
        max_frame_bytes=int(args.max_frame_mb * 2**20),
        snapshot_dir=args.snapshot_dir,
        fsync=not args.no_fsync,
        snapshot_every_inserts=args.snapshot_every,
        **{
            field: type(getattr(BufferConfig, field))(
                getattr(args, flag[2:].replace("-", "_")) * scale
            )
            for flag, field, _, scale, _ in LIMITS
        },
        sample_timeout_s=args.sample_timeout,
        insert_timeout_s=args.insert_timeout,
        max_sample_episodes=args.max_sample,
        repair=args.repair,
        metrics_port=args.metrics_port,
        seed=args.seed,
        store_state=not args.no_state,
    )
    cfg.validate()
    return cfg


def cmd_serve(args: argparse.Namespace) -> int:
    from buffer_service.runner import run
    from buffer_service.storage import StorageError, WriteError

    try:
        cfg = build_config(args)
    except (ValueError, TypeError) as e:
        log.error("credit buffer serve: %s", e)
        return 2
    try:
        failed = run(cfg, port_file=args.port_file)
    except StorageError as e:
        log.error("credit buffer serve: refusing to start: %s", e)
        return 2
    except WriteError as e:
        log.error("credit buffer serve: cannot start: %s: %s", e.code, e)
        return 2
    except OSError as e:  # e.g. the port is taken, or the folder cannot be read
        log.error("credit buffer serve: cannot start: %s", e)
        return 2
    if failed:
        log.error("credit buffer serve: stopped without its final snapshot: %s", failed)
        return 1
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    """Print the folder's report as JSON; exit 0 when intact, 1 when anything is damaged."""
    from buffer_service.verify import verify

    try:
        tables = tuple(parse_table(t) for t in args.table) or None
        report = verify(args.dir, tables)
    except (ValueError, TypeError, FileNotFoundError) as e:
        log.error("credit buffer verify: %s", e)
        return 2
    print(json.dumps(report, indent=2))
    return 0 if report["ok"] else 1
