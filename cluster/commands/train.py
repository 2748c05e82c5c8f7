"""`credit train`: train one algorithm on one env and write config, metrics, summary, checkpoint.

Outputs under --out: config.yaml, metrics.jsonl (one JSON object per evaluation),
summary.json and checkpoint/ (also refreshed every run.save_interval env steps); with
run.loggers, TensorBoard event files in tensorboard/ and a W&B run
(`cluster.metrics.run_loggers`).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import yaml

from actors.envs.registry import env_name, is_map_file
from cluster.commands import add_command
from cluster.config.schema import ConfigError
from cluster.config.shipped import default_files, recipe_file
from cluster.config.train import TrainConfig, load_train_config
from cluster.core import EvalRecord, write_json
from cluster.errors import UsageError
from cluster.launch.local import LocalTrainer
from cluster.metrics.run_loggers import RunLoggers, check_installed
from cluster.process import configure
from learner.common import NonFiniteLossError
from learner.registry import ALGOS

log = logging.getLogger(__name__)


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments shared by every command that builds a TrainConfig."""
    p.add_argument("--algo", help=f"algorithm, one of: {', '.join(sorted(ALGOS))} (default rdn)")
    p.add_argument(
        "--env",
        help="env id, see `credit env list` (default matrix/four_game), or the path of a "
        "skirmish map file (.yaml)",
    )
    p.add_argument(
        "--config",
        action="append",
        default=[],
        metavar="FILE",
        help="YAML config layered on the shipped defaults (repeatable)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one config key, e.g. algo.lr=0.001 (repeatable)",
    )


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "train",
        "Train one algorithm on one env; writes OUT/config.yaml, metrics.jsonl, "
        "summary.json and checkpoint/ (cluster mode adds buffer/, cluster.json and "
        "targets.json).",
    )
    add_run_arguments(p)
    p.add_argument("--seed", type=int, help="random seed (run.seed)")
    p.add_argument("--t-max", type=int, help="env steps to train (run.t_max)")
    p.add_argument("--out", default=None, help="output folder (default runs/<algo>_<env>_s<seed>)")
    p.add_argument("--resume", metavar="DIR", help="continue the run in DIR from its checkpoint")
    p.add_argument(
        "--print-config",
        action="store_true",
        help="print the resolved config (every layer applied) as YAML and exit; writes nothing",
    )
    p.add_argument(
        "--mode",
        choices=["local", "cluster"],
        default="local",
        help="local: one process; cluster: Ray rollout actors + the buffer service",
    )
    p.add_argument("--actors", type=int, help="cluster mode: rollout actors (cluster.actors)")
    p.add_argument(
        "--address",
        help="cluster mode: Ray address to join ('auto' = the one `credit cluster up` started); "
        "default: start a private local Ray instance on 127.0.0.1",
    )
    p.set_defaults(func=cmd_train)


def _overrides(args: argparse.Namespace) -> list[str]:
    sets = list(args.set)
    if args.seed is not None:
        sets.append(f"run.seed={args.seed}")
    if args.t_max is not None:
        sets.append(f"run.t_max={args.t_max}")
    if getattr(args, "actors", None) is not None:
        sets.append(f"cluster.actors={args.actors}")
    return sets


def cmd_train(args: argparse.Namespace) -> int:
    if args.resume:
        out = Path(args.resume)
        if not (out / "checkpoint" / "learner.pt").exists():
            raise ConfigError(f"--resume {out}: no checkpoint at {out / 'checkpoint'}")
        cfg = load_train_config(
            args.algo, args.env, [str(out / "config.yaml"), *args.config], _overrides(args)
        )
    else:
        cfg = load_train_config(args.algo, args.env, args.config, _overrides(args))
        env = env_name(cfg.env.id) if is_map_file(cfg.env.id) else cfg.env.id.replace("/", "-")
        name = f"{cfg.algo_name}_{env}_s{cfg.run.seed}"
        out = Path(args.out or Path("runs") / name)
    if args.print_config:
        print(config_text(cfg, args.config), end="")
        return 0
    check_installed(cfg.run.loggers)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(config_text(cfg, args.config))
    configure(cfg.run)  # this process's torch threads and seed, its allocator
    if args.mode == "cluster":
        trainer, records = _train_cluster(cfg, out, args)
    else:
        trainer = LocalTrainer(cfg, checkpoint_dir=out / "checkpoint")
        if args.resume:
            trainer.restore(out / "checkpoint")
            log.info("resumed %s at t_env=%d", out, trainer.core.t_env)
        records = _run(trainer, out, bool(args.resume))
        trainer.save(out / "checkpoint")
    last = records[-1]
    core = trainer.core
    summary = {
        "algo": cfg.algo_name,
        "env": cfg.env.id,
        "seed": cfg.run.seed,
        "mode": args.mode,
        "t_env": core.t_env,
        "episodes": core.episodes,
        "updates": core.learner.updates,
        "wall_s": round(core.wall_s, 3),
        "final_test_return_mean": last.test_return_mean,
        "final_test_won_mean": last.test_won_mean,
        "dropped_stale_episodes": trainer.stats.dropped_stale,  # run.max_policy_lag
    }
    if args.mode == "cluster":
        summary["actors"] = cfg.cluster.actors
        summary["actor_restarts"] = trainer.restarts
        summary["buffer_restarts"] = trainer.buffer.restarts
    write_json(out / "summary.json", summary)
    kept = ", best/" if cfg.run.keep_best else ""
    print(f"results in {out}: summary.json, metrics.jsonl, config.yaml, checkpoint/{kept}")
    return 0


def config_text(cfg: TrainConfig, user_files: list[str]) -> str:
    """`cfg` as YAML, headed by comments naming the layers it was resolved from."""
    layers = ["dataclass defaults", *map(str, default_files(cfg.algo_name, cfg.env.id))]
    layers += [str(f) for f in [recipe_file(cfg.algo_name, cfg.recipe)] if f is not None]
    layers += [*user_files, "--set overrides"]
    head = "# Resolved config. Layers, later ones winning:\n"
    head += "".join(f"#   {layer}\n" for layer in layers)
    return head + yaml.safe_dump(cfg.to_yaml_dict(), sort_keys=False)


def _run(trainer, out: Path, append: bool) -> list[EvalRecord]:
    """Train with `trainer` (local or cluster), appending evaluations to metrics.jsonl; a
    final evaluation at the last t_env if the schedule did not end on one."""
    core = trainer.core
    records: list[EvalRecord] = []
    cfg = core.ctx.cfg
    loggers = RunLoggers(cfg.run.loggers, out, cfg.to_yaml_dict(), append)
    try:

        def on_eval(recs: list[EvalRecord]) -> None:
            records.extend(recs)
            loggers.log(recs, core.take_metric_means())

        log.info(
            "training %s on %s for %d env steps -> %s",
            cfg.algo_name,
            cfg.env.id,
            cfg.run.t_max,
            out,
        )
        try:
            trainer.train(on_eval=on_eval, progress=True)
        except NonFiniteLossError as e:
            where = out / "checkpoint"
            kept = (
                f"the last good checkpoint in {where} is untouched"
                if where.exists()
                else "no checkpoint was written yet"
            )
            raise NonFiniteLossError(f"training stopped: {e}; {kept}") from None
        if not records or records[-1].t_env != core.t_env:
            on_eval(core.evaluate())
    finally:
        loggers.close()
    return records


def _train_cluster(cfg, out: Path, args: argparse.Namespace):
    from cluster.launch import ray_cluster

    ray_cluster.apply_ray_environment()  # before anything imports ray: it reads them at import
    from cluster.launch.cluster import ClusterTrainer

    try:
        where = ray_cluster.connect(args.address, num_cpus=max(2, cfg.cluster.actors + 1))
    except ray_cluster.ClusterError as e:
        raise UsageError(str(e)) from None
    log.info("%s", where)
    trainer = ClusterTrainer(cfg, out)
    if args.resume:
        trainer.restore(out / "checkpoint")
        log.info("resumed %s at t_env=%d", out, trainer.core.t_env)
    try:
        trainer.start()
        records = _run(trainer, out, bool(args.resume))
        trainer.save(out / "checkpoint")
    finally:
        trainer.shutdown()
    return trainer, records
