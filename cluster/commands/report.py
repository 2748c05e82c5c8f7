"""`credit report DIR`: the aggregate statistics and one self-contained HTML page of any
`credit repro ...` experiment, finished or still running, from its evaluation logs alone."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cluster.commands import add_command
from cluster.config.train import load_train_config
from cluster.core import write_json
from cluster.errors import UsageError
from cluster.repro import aggregate
from cluster.repro import curves as repro_curves
from cluster.repro import matrix as repro_matrix
from cluster.repro import report as repro_report


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "report",
        "Rebuild the aggregate statistics (IQM with stratified bootstrap intervals, "
        "probability of improvement, performance profiles; rliable) of a `credit repro` "
        "experiment from DIR/evals/*.jsonl, finished or partial, and write DIR/report.html "
        "(one self-contained page: tables and figures inline) and DIR/aggregate_*.png; "
        "DIR/summary.json, when there is one, gets the new aggregate entry.",
    )
    p.add_argument("dir", metavar="DIR", help="the experiment's --out folder")
    p.add_argument(
        "--bootstrap-reps",
        type=int,
        default=aggregate.REPS,
        help=f"bootstrap draws of each interval (default {aggregate.REPS})",
    )
    p.add_argument("--seed", type=int, default=aggregate.SEED, help="bootstrap seed (default 0)")
    p.set_defaults(func=cmd_report)


def read_logs(log_dir: Path) -> tuple[list[str], list[str], bool]:
    """(envs, algos, has_wins) named by the first line of each non-empty evals/*.jsonl."""
    envs, algos, wins = {}, {}, False
    for path in sorted(log_dir.glob("*.jsonl")):
        first = next((x for x in path.read_text().splitlines() if x.strip()), None)
        if first is None:
            continue
        env, _, algo = path.stem.replace("-", "/", 1).partition("__")
        try:
            row = json.loads(first)
        except json.JSONDecodeError:
            row = None
        if not isinstance(row, dict) or "t_env" not in row or "returns" not in row:
            raise UsageError(f"{path}: not an evaluation log of `credit repro`")
        envs[row.get("env", env)], algos[row.get("algo", algo)] = None, None
        wins = wins or "won" in row
    return list(envs), list(algos), wins


def cmd_report(args: argparse.Namespace) -> int:
    out = Path(args.dir)
    if args.bootstrap_reps < 1:
        raise UsageError(f"--bootstrap-reps must be >= 1, got {args.bootstrap_reps}")
    envs, algos, wins = read_logs(out / "evals")
    if not envs:
        raise UsageError(f"no evaluation logs in {out / 'evals'} (a `credit repro --out` folder)")
    best = {g: aggregate.max_return(g, load_train_config(algos[0], g).env.args) for g in envs}
    figures = []
    if wins:
        curves = repro_curves.load_evals(out / "evals", algos, envs)
        summary = repro_curves.summarise(curves)
        scores = aggregate.curve_scores(curves, best, repro_curves.LAST)
        for g in envs:
            png = repro_report.figure_png(repro_curves.plot, curves, g)
            figures.append((f"{g}: learning curves", png))
    else:
        curves = repro_matrix.load_evals(out / "evals", algos, envs)
        summary = repro_matrix.summarise(curves, best)
        scores = aggregate.matrix_scores(curves, best)
        for g in envs:
            figures.append(
                (f"{g}: test return", repro_report.figure_png(repro_matrix.plot, curves, g))
            )
    title = f"credit report: {out}"
    page = repro_report.write_outputs(
        out, title, scores, summary, figures, args.bootstrap_reps, args.seed
    )
    if (out / "summary.json").exists():
        kept = json.loads((out / "summary.json").read_text())
        kept["aggregate"] = summary["aggregate"]
        write_json(out / "summary.json", kept)
    print(f"{page}: {len(curves)} (algorithm, env) pairs; aggregate_*.png beside it")
    return 0
