"""`credit sweep`: grid or random search over config keys and seeds on Ray Tune; each trial is
a `credit train` run; the result is a table of configurations ranked by a statistic over
their seeds, with intervals (`cluster.repro.sweep`)."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import yaml

from actors.envs.registry import env_family
from cluster.commands import add_command
from cluster.commands.train import add_run_arguments
from cluster.config.train import load_train_config
from cluster.core import write_json
from cluster.errors import UsageError
from cluster.launch.ray_cluster import ClusterError
from cluster.repro import aggregate

log = logging.getLogger(__name__)

RANDOM = ("choice", "uniform", "loguniform", "randint")


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "sweep",
        "Grid or random search over config keys and seeds on Ray Tune: every (configuration, "
        "seed) is a `credit train` run in OUT/trials/<name>/ (its usual outputs); trials "
        "whose process dies are retried, the same command again resumes an interrupted sweep; "
        "writes OUT/sweep.json, the configurations ranked by the IQM over seeds of --metric "
        "with bootstrap intervals. Needs ray[tune] (pip install 'credit[tune]').",
    )
    add_run_arguments(p)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--grid",
        action="append",
        default=[],
        metavar="KEY=V1,V2,...",
        help="grid search over these values of KEY (YAML each; repeatable: the cross product)",
    )
    for kind in RANDOM:
        p.add_argument(
            f"--{kind}",
            action="append",
            default=[],
            metavar="KEY=" + ("V1,V2,..." if kind == "choice" else "LOW,HIGH"),
            help=f"random search: KEY drawn with tune.{kind} (repeatable; see --samples)",
        )
    p.add_argument(
        "--samples", type=int, default=4, help="random configurations per grid point (4)"
    )
    p.add_argument("--search-seed", type=int, default=0, help="seed of the random draws (0)")
    p.add_argument("--seeds", type=int, default=3, help="seeds (run.seed 0..N-1) per config (3)")
    p.add_argument("--t-max", type=int, help="env steps per trial (run.t_max)")
    p.add_argument(
        "--metric",
        default=None,
        help="metrics.jsonl field ranked on (default test_won_mean on maps with wins, else "
        "test_return_mean)",
    )
    p.add_argument("--last", type=int, default=1, help="each trial's mean of its last N evals (1)")
    p.add_argument("--bootstrap-reps", type=int, default=aggregate.REPS, help="bootstrap draws")
    p.add_argument(
        "--address",
        default=None,
        metavar="auto|HOST:PORT",
        help="run the trials on this Ray cluster ('auto' = the one `credit cluster up` "
        "started); default: a private local Ray instance on 127.0.0.1 with --workers CPUs",
    )
    p.add_argument("--workers", type=int, default=2, help="CPUs of the private instance (2)")
    p.add_argument("--cpus-per-trial", type=float, default=1.0, help="CPUs per trial (1)")
    p.add_argument(
        "--max-failures", type=int, default=3, help="restarts of a trial whose process dies (3)"
    )
    p.set_defaults(func=cmd_sweep)


def _key_values(spec: str, flag: str) -> tuple[str, list]:
    key, sep, raw = spec.partition("=")
    if not sep or not key or not raw:
        raise UsageError(f"--{flag} takes KEY=V1,V2,..., got {spec!r}")
    return key.strip(), [yaml.safe_load(v) for v in raw.split(",")]


def search_space(args: argparse.Namespace) -> tuple[dict, dict]:
    """(grid {key: values}, random {key: tune Domain}) from the command line."""
    from ray import tune

    grid = dict(_key_values(s, "grid") for s in args.grid)
    random = {}
    for kind in RANDOM:
        for spec in getattr(args, kind):
            key, values = _key_values(spec, kind)
            if kind != "choice" and len(values) != 2:
                raise UsageError(f"--{kind} takes KEY=LOW,HIGH, got {spec!r}")
            random[key] = tune.choice(values) if kind == "choice" else getattr(tune, kind)(*values)
    if not grid and not random:
        raise UsageError("name at least one key to search: --grid, --choice, --uniform, ...")
    return grid, random


def cmd_sweep(args: argparse.Namespace) -> int:
    from cluster.launch import ray_cluster

    ray_cluster.apply_ray_environment()  # before anything imports ray
    try:
        # the tune extra's packages (pandas, pyarrow, ...) may be missing
        import ray.tune
    except ImportError as e:
        raise UsageError(f"credit sweep needs Ray Tune: pip install 'credit[tune]' ({e})") from None
    from cluster.repro import sweep as tune_sweep

    sweep, metric = _plan(args, tune_sweep)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        where = ray_cluster.connect(
            args.address, num_cpus=args.workers, runtime_env=_runtime_env(args)
        )
    except ClusterError as e:
        raise UsageError(str(e)) from None
    log.info("%s; %d configs x %d seeds as Ray Tune trials", where, len(sweep.points), args.seeds)
    try:
        tune_sweep.run(sweep, out, args.cpus_per_trial, args.max_failures)
    finally:
        import ray

        ray.shutdown()
    table = tune_sweep.rank(sweep, out, metric, args.last, args.bootstrap_reps, aggregate.SEED)
    bootstrap = {"reps": args.bootstrap_reps, "seed": aggregate.SEED}
    write_json(
        out / "sweep.json",
        {"metric": metric, "last": args.last, "bootstrap": bootstrap, "ranking": table},
    )
    print(f"rank  IQM {metric} [95% CI]  runs  config")
    for r in table:
        score = f"{r['iqm']:.3f} [{r['ci'][0]:.3f}, {r['ci'][1]:.3f}]" if r["runs"] else "-"
        print(f"{r['rank']:4d}  {score:24s}  {r['runs']}/{args.seeds}  {json.dumps(r['config'])}")
    print(f"results in {out}: sweep.json, trials/<name>/ (credit train's outputs), tune/")
    return 0 if all(r["missing"] == 0 for r in table) else 1


def _plan(args: argparse.Namespace, tune_sweep):
    """The checked Sweep and the metric ranked on (UsageError / ConfigError when bad)."""
    for name in ("seeds", "samples", "last", "bootstrap_reps", "workers", "max_failures"):
        low = 0 if name == "max_failures" else 1
        if getattr(args, name) < low:
            flag = name.replace("_", "-")
            raise UsageError(f"--{flag} must be >= {low}, got {getattr(args, name)}")
    grid, random = search_space(args)
    points = tune_sweep.points(grid, random, args.samples, args.search_seed)
    sets = [*args.set, *([f"run.t_max={args.t_max}"] if args.t_max else [])]
    sweep = tune_sweep.Sweep(
        args.algo, args.env, tuple(args.config), tuple(sets), tuple(points), args.seeds
    )
    for p in points:  # every configuration checked before any trial starts
        cfg = load_train_config(args.algo, args.env, args.config, sweep.argv_sets(p))
    wins = env_family(cfg.env.id) != "matrix"
    return sweep, args.metric or ("test_won_mean" if wins else "test_return_mean")


def _runtime_env(args: argparse.Namespace) -> dict | None:
    """Ship this checkout's packages to the nodes of a cluster (as `credit repro` does)."""
    if not args.address:
        return None
    from cluster.repro.fanout_ray import runtime_env

    return runtime_env(True)
