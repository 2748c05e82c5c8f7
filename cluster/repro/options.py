"""What every `credit repro` experiment shares on its command line: where the (algorithm,
env) pairs run and how they checkpoint (`add_run_options`, as a FanOutConfig and a
ResumeConfig), and the checks of its --algos and --envs."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from actors.envs.registry import env_name, is_map_file
from cluster.errors import UsageError
from cluster.repro import groups as repro_groups
from cluster.repro import resume as repro_resume
from cluster.repro.aggregate import REPS
from cluster.repro.pairs import FanOutConfig
from cluster.repro.resume import ResumeConfig
from learner.registry import ALGOS

log = logging.getLogger(__name__)


def add_run_options(m: argparse.ArgumentParser) -> None:
    """Where the (algorithm, env) pairs run, and --set; shared by every experiment."""
    m.add_argument(
        "--workers",
        type=int,
        default=2,
        help="local processes running pairs in parallel (without --address)",
    )
    m.add_argument(
        "--address",
        default=None,
        metavar="auto|HOST:PORT",
        help="run each (algorithm, env) pair as a Ray task on this cluster: 'auto' = the one "
        "`credit cluster up` started (else Ray's discovery, e.g. RAY_ADDRESS), or a head's "
        "HOST:PORT; results still land in --out (default: local processes)",
    )
    m.add_argument(
        "--cpus-per-pair",
        type=float,
        default=1.0,
        help="with --address: CPUs each pair's task asks for (default 1; a pair uses "
        "run.torch_threads threads, 1 unless set)",
    )
    m.add_argument(
        "--max-retries",
        type=int,
        default=3,
        help="with --address: restarts of a pair whose worker process or node dies (default 3)",
    )
    m.add_argument(
        "--no-ship-code",
        dest="ship_code",
        action="store_false",
        help="with --address: run the credit installed on the nodes instead of uploading this "
        "checkout's packages to them",
    )
    m.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override for every run",
    )
    m.add_argument(
        "--bootstrap-reps",
        type=int,
        default=REPS,
        help=f"bootstrap draws of each aggregate interval in summary.json (default {REPS})",
    )
    m.add_argument(
        "--checkpoint-every",
        type=int,
        default=repro_resume.CHECKPOINT_EVERY,
        metavar="STEPS",
        help="each pair checkpoints its whole state (networks, optimisers, replay, random "
        "states, evaluation log) to OUT/resume/<env>__<algo>/ every STEPS env steps "
        f"(default {repro_resume.CHECKPOINT_EVERY:,}; 0: never); running the same command "
        "again continues unfinished pairs from there and skips finished ones",
    )


def add_seed_group_option(m: argparse.ArgumentParser) -> None:
    """--seed-group: one part of each pair's seeds, trained by this command."""
    m.add_argument(
        "--seed-group",
        type=int,
        default=0,
        metavar="G",
        help="train this command's --seeds as seed group G of each pair (0.."
        f"{repro_groups.MAX_GROUP}, default 0), so that one pair's seeds can be split over "
        "several runs, one after the other or at once, into the same --out: group G trains "
        f"with run.seed + G*{repro_groups.STRIDE:,} (no two groups share a random stream; "
        "a group too large to keep to its own seeds is refused) and keeps its own files "
        "(OUT/evals/<env>__<algo>.g<G>.jsonl, OUT/resume/, OUT/pairs/; group 0's are the "
        "names without .g<G>). The summary merges every group of a pair into one curve: "
        "seeds in group order, at the evaluations every group has",
    )


def seed_group_overrides(args: argparse.Namespace, cfgs: list) -> list[str]:
    """The overrides of --seed-group (run.seed of the group; none for group 0) after checking
    that the group keeps to its own seeds in every pair's config `cfgs` (UsageError if not)."""
    group = args.seed_group
    if group and args.summarise_only:
        raise UsageError(
            "--summarise-only merges every seed group of each pair found in OUT/evals; "
            "drop --seed-group"
        )
    bases = {c.run.seed for c in cfgs}
    if len(bases) > 1:
        raise UsageError(f"--seed-group: the pairs' configs set run.seed differently: {bases}")
    for c in cfgs:
        run = c.run
        repro_groups.check(group, run.seed, args.seeds, run.num_envs, run.test_episodes)
    return [f"run.seed={repro_groups.group_seed(group, bases.pop())}"] if group else []


def fan_out_config(args: argparse.Namespace) -> FanOutConfig:
    """The run options of a repro command as a checked FanOutConfig (UsageError if bad)."""
    if args.bootstrap_reps < 1:
        raise UsageError(f"--bootstrap-reps must be >= 1, got {args.bootstrap_reps}")
    cfg = FanOutConfig(
        workers=args.workers,
        address=args.address or None,
        cpus_per_pair=args.cpus_per_pair,
        max_retries=args.max_retries,
        ship_code=args.ship_code,
    )
    try:
        cfg.validate()
    except ValueError as e:
        raise UsageError(str(e)) from None
    return cfg


def resume_config(args: argparse.Namespace, out: Path, overrides: list[str]) -> ResumeConfig:
    """Where the pairs checkpoint and record themselves (UsageError for a bad interval)."""
    if args.checkpoint_every < 0:
        raise UsageError(f"--checkpoint-every must be >= 0, got {args.checkpoint_every}")
    commit = repro_resume.code_commit()
    log.info("code at commit %s", commit)
    settings = {"seeds": args.seeds, "overrides": list(overrides)}
    return ResumeConfig(str(out.resolve()), args.checkpoint_every, commit, settings)


def check_algos(algos: list[str]) -> None:
    for a in algos:
        if a not in ALGOS:
            raise UsageError(
                f"unknown algorithm {a!r}; valid algorithms: {', '.join(sorted(ALGOS))}"
            )


def custom_as_file(envs: list[str], sets: list[str]) -> tuple[list[str], list[str]]:
    """`skirmish/custom` with `--set env.args.map_file=PATH` is the map file PATH given as an
    env, so that it is named, logged and charted as one (and the override does not reach the
    other envs). Returns the envs and the remaining overrides."""
    key = "env.args.map_file="
    files = [s.removeprefix(key) for s in sets if s.startswith(key)]
    if not files or "skirmish/custom" not in envs:
        return envs, sets
    rest = [s for s in sets if not s.startswith(key)]
    return [files[-1] if g == "skirmish/custom" else g for g in envs], rest


def check_env_names(envs: list[str], fan: FanOutConfig) -> None:
    """Each env must name its own plot (a map file by its stem), and on a cluster a map file
    must be given by its absolute path: the pairs run in other working directories."""
    seen: dict[str, str] = {}
    for g in envs:
        if env_name(g) in seen and seen[env_name(g)] != g:
            raise UsageError(
                f"--envs: {seen[env_name(g)]!r} and {g!r} would share the plot name "
                f"{env_name(g)!r}; rename one map file"
            )
        seen[env_name(g)] = g
        if fan.address and is_map_file(g) and not Path(g).is_absolute():
            raise UsageError(
                f"--envs {g!r}: with --address give a map file by its absolute path (the "
                "pairs run in other working directories; on other nodes the file must be at "
                "that path too)"
            )
