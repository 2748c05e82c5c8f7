"""`credit inspect relevance --run DIR`: per-agent credit of a trained run (see
cluster/inspect/relevance.py), as JSON, PNG and an animated GIF of one battle;
`credit inspect rdn-credit`: whether RDN's split credits agents for their own actions, while
it trains (cluster/inspect/rdn_credit.py)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from cluster.commands import add_command
from cluster.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "inspect",
        "Look inside trained runs; writes what it finds next to them (RUN/relevance/ by default).",
    )
    isub = p.add_subparsers(dest="inspect_command", required=True, metavar="WHAT")
    r = add_command(
        isub,
        "relevance",
        "Show who gets the credit (RDN's LRP shares, VDN's utilities, QMIX's mixer "
        "gradients) over greedy episodes of a trained run; prints a JSON summary and writes "
        "relevance.json, relevance.png and relevance.gif to --out.",
    )
    r.add_argument(
        "--run",
        required=True,
        help="a `credit train` output folder, or a checkpoint folder "
        "(e.g. OUT/checkpoints/<env>__<algo> of `credit repro ... --checkpoints`)",
    )
    r.add_argument("--episodes", type=int, default=8, help="greedy episodes to play (8)")
    r.add_argument("--member", type=int, default=0, help="seed of a seed-batched checkpoint (0)")
    r.add_argument("--seed", type=int, default=0, help="env seed of the episodes (0)")
    r.add_argument("--gif-episode", type=int, default=0, help="which episode the GIF shows")
    r.add_argument("--max-frames", type=int, default=150, help="GIF frames at most (150)")
    r.add_argument("--out", help="output folder (default RUN/relevance)")
    r.set_defaults(func=cmd_relevance)
    c = add_command(
        isub,
        "rdn-credit",
        "Train RDN (seeds batched) and, at every evaluation, measure on a replay batch how "
        "much each agent's LRP target moves with its own action against the critic; prints "
        "one JSON line per evaluation and writes them to --out.",
    )
    c.add_argument("--env", default="skirmish/3m", help="env id or map file (skirmish/3m)")
    c.add_argument("--seeds", type=int, default=3, help="seeds, batched in one trainer (3)")
    c.add_argument("--t-max", type=int, default=60_000, help="env steps (60000)")
    c.add_argument("--out", required=True, help="the JSON lines file to write")
    c.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="config override"
    )
    c.set_defaults(func=cmd_rdn_credit)


def cmd_relevance(args: argparse.Namespace) -> int:
    from cluster.inspect.relevance import inspect

    if args.episodes < 1 or args.max_frames < 1:
        raise UsageError("--episodes and --max-frames must be >= 1")
    run = Path(args.run)
    out = Path(args.out) if args.out else run / "relevance"
    summary = inspect(
        run, out, args.episodes, args.member, args.seed, args.gif_episode, args.max_frames
    )
    print(json.dumps({k: summary[k] for k in ("algo", "env", "credit", "win_rate", "groups")}))
    print(f"results in {out}: relevance.json, relevance.png, relevance.gif")
    return 0


def cmd_rdn_credit(args: argparse.Namespace) -> int:
    from cluster.inspect.rdn_credit import run

    if args.seeds < 1:
        raise UsageError(f"--seeds must be >= 1, got {args.seeds}")
    lines = run(args.env, args.seeds, args.t_max, args.set, Path(args.out), print)
    print(f"{lines} evaluations in {args.out}", file=sys.stderr)
    return 0
