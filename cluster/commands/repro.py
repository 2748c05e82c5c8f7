"""`credit repro matrix`: the dissertation's matrix-game experiment (Fig. 5.3) for every algorithm;
`credit repro emcac`: the dissertation's EM-CAC ablation (Table 5.2, Figs. 5.10-5.13);
`credit repro smac`: the value family and RDN on SMAC-like maps (results/smac/);
`credit repro redundancy`: the dissertation's redundant-agents experiment (Table 5.1,
Figs. 5.6-5.9)."""

from __future__ import annotations

import argparse
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

from actors.envs.registry import env_name
from cluster.commands import add_command
from cluster.config.train import load_train_config
from cluster.core import write_json
from cluster.errors import UsageError
from cluster.launch.ray_cluster import UnreachableClusterError
from cluster.repro import curves as repro_curves
from cluster.repro import emcac as repro_emcac
from cluster.repro import matrix as repro_matrix
from cluster.repro import redundancy as repro_redundancy
from cluster.repro import report as repro_report
from cluster.repro import smac as repro_smac
from cluster.repro import table52 as repro_table52
from cluster.repro import table52_md as repro_table52_md
from cluster.repro.aggregate import SEED, curve_scores, matrix_scores, max_return
from cluster.repro.options import (
    add_run_options,
    add_seed_group_option,
    check_algos,
    check_env_names,
    custom_as_file,
    fan_out_config,
    resume_config,
    seed_group_overrides,
)
from cluster.repro.verdict import Plan, describe

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "repro",
        "Reproduce the dissertation's experiments, in local processes or as Ray tasks on a cluster "
        "(--address); each writes summary.json, its curves and PNG plots under --out.",
    )
    rsub = p.add_subparsers(dest="repro_command", required=True, metavar="EXPERIMENT")
    m = add_command(
        rsub,
        "matrix",
        "Seed Fig. 5.3: train every algorithm on both matrix games, in local processes or "
        "on a Ray cluster (--address); writes OUT/evals/*.jsonl as it runs, then "
        "summary.json, curves.json and matrix_<game>.png.",
    )
    m.add_argument("--seeds", type=int, default=8, help="seeds per algorithm and game (default 8)")
    m.add_argument("--out", required=True, help="output folder")
    m.add_argument(
        "--algos", default=",".join(repro_matrix.ALGOS), help="comma-separated algorithms"
    )
    m.add_argument(
        "--games", default=",".join(repro_matrix.GAMES), help="comma-separated matrix env ids"
    )
    m.add_argument(
        "--t-max",
        type=int,
        default=None,
        help="env steps per run (default: cluster/config/layers/envs/matrix.yaml)",
    )
    add_run_options(m)
    add_seed_group_option(m)
    m.add_argument(
        "--summarise-only",
        action="store_true",
        help="train nothing: rebuild summary.json, the plots and report.html from "
        "OUT/evals/*.jsonl, every seed group of a pair merged (curves.json, which holds "
        "RDN's diagnostics, is kept)",
    )
    m.set_defaults(func=cmd_matrix)
    register_emcac(rsub)


def _run(run: Callable[[], list]) -> list:
    """Run the pairs; an unreachable cluster is a usage error (exit 2, no traceback)."""
    try:
        return run()
    except UnreachableClusterError as e:
        raise UsageError(str(e)) from None


def register_emcac(rsub: argparse._SubParsersAction) -> None:
    m = _register_curves(
        rsub,
        "emcac",
        "Seed Table 5.2: train CAC, E-CAC, EM-CAC, COMA and QMIX on skirmish maps; writes "
        "OUT/evals/*.jsonl as it runs, then summary.json (with the table52 entry: ours beside "
        "the dissertation's Table 5.2 and its ordering claims), table52.md, curves.json and "
        "one PNG per map.",
        repro_emcac,
        default_seeds=8,
    )
    m.set_defaults(func=cmd_emcac)
    _register_curves(
        rsub,
        "smac",
        "Train IQL, VDN, QMIX, QMIX-nostate and RDN on SMAC-like maps (skirmish or real SMAC); "
        "writes OUT/evals/*.jsonl as it runs, then summary.json, curves.json and one PNG per map.",
        repro_smac,
        default_seeds=3,
    )
    m = _register_curves(
        rsub,
        "redundancy",
        "Seed Table 5.1 and Figs. 5.6-5.9: train the value family and RDN on bane_vs_bane "
        "variants; writes OUT/evals/*.jsonl as it runs, then summary.json, curves.json, one "
        "PNG per map and the redundancy_*.png figures.",
        repro_redundancy,
        default_seeds=3,
    )
    m.add_argument(
        "--zerglings",
        default="",
        metavar="N,N,...",
        help="also generated maps skirmish/bane_z<N>: bane_vs_bane with N allied zerglings "
        "(the enemy keeps 20 zerglings + 4 banelings); --envs '' runs only these",
    )
    m.set_defaults(
        func=lambda args: cmd_curves(
            args,
            "redundancy",
            repro_redundancy,
            extra_envs=repro_redundancy.zergling_envs(args.zerglings),
            figures=repro_redundancy.write_figures,
        )
    )


def cmd_emcac(args: argparse.Namespace) -> int:
    """`credit repro emcac`: the curves, and Table 5.2 beside the dissertation's."""
    repro_table52.check_envs([g for g in args.envs.split(",") if g])
    return cmd_curves(args, "emcac", repro_emcac, tables=repro_table52_md.write)


def _register_curves(
    rsub: argparse._SubParsersAction,
    name: str,
    help_text: str,
    experiment: ModuleType,
    default_seeds: int,
) -> argparse.ArgumentParser:
    m = add_command(rsub, name, help_text)
    m.add_argument(
        "--envs",
        default=",".join(experiment.ENVS),
        help="comma-separated skirmish/smac env ids or paths of skirmish map files (.yaml)",
    )
    m.add_argument("--algos", default=",".join(experiment.ALGOS), help="comma-separated algorithms")
    m.add_argument(
        "--seeds",
        type=int,
        default=default_seeds,
        help=f"seeds per algorithm and env, batched in one set of tensors ({default_seeds})",
    )
    m.add_argument(
        "--t-max",
        type=int,
        default=None,
        help="env steps per run (default: the env's YAML); with --summarise-only, each pair's "
        "evaluations up to its first at or past T_MAX",
    )
    m.add_argument(
        "--test-interval",
        type=int,
        default=None,
        help="env steps between evaluations (default: the env's YAML)",
    )
    m.add_argument("--out", required=True, help="output folder")
    add_run_options(m)
    add_seed_group_option(m)
    m.add_argument(
        "--summarise-only",
        action="store_true",
        help="train nothing: rebuild summary.json and plots from OUT/evals/*.jsonl, every "
        "seed group of a pair merged into one curve",
    )
    m.add_argument(
        "--checkpoints",
        action="store_true",
        help="save each pair's final checkpoint (all seeds; networks, optimisers and counters, "
        "not the replay) to OUT/checkpoints/<env>__<algo>/ (for `credit inspect relevance --run`)",
    )
    m.set_defaults(func=lambda args: cmd_curves(args, name, experiment))
    return m


def cmd_curves(
    args: argparse.Namespace,
    name: str,
    experiment: ModuleType,
    extra_envs: list[str] = (),
    figures: Callable[[list, list[str], Path, dict, Plan], list[str]] | None = None,
    tables: Callable[[list, Path, dict, int, int], list[str]] | None = None,
) -> int:
    """`credit repro emcac` / `smac` / `redundancy`: curves of every (algo, env) pair, then
    the per-env plots and, with `figures`, the experiment's own figures over every env
    (which may add to the summary; the plan tells it which pairs were to run how far); with
    `tables`, the experiment's own tables (added to the summary and written into OUT)."""
    algos = [a for a in args.algos.split(",") if a]
    envs = [g for g in args.envs.split(",") if g] + [g for g in extra_envs if g]
    envs, sets = custom_as_file(envs, list(args.set))
    check_algos(algos)
    if not algos or not envs:
        raise UsageError("--algos and --envs must name at least one algorithm and env")
    if args.seeds < 1:
        raise UsageError(f"--seeds must be >= 1, got {args.seeds}")
    fan = fan_out_config(args)
    check_env_names(envs, fan)
    overrides = sets + ([f"run.t_max={args.t_max}"] if args.t_max else [])
    if args.test_interval:
        overrides.append(f"run.test_interval={args.test_interval}")
    # validates every (algo, env) config before any training starts
    cfgs = [load_train_config(a, g, [], overrides) for g in envs for a in algos]
    t_max = sum(c.run.t_max for c in cfgs)
    keys = [(g, a) for g in envs for a in algos]
    plan = Plan(
        {k: c.run.t_max for k, c in zip(keys, cfgs, strict=True)},
        args.bootstrap_reps,
        seeds=args.seeds,
    )
    overrides += seed_group_overrides(args, cfgs)
    out = Path(args.out)
    (out / "evals").mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    if args.summarise_only:
        curves = repro_curves.load_evals(out / "evals", algos, envs, until=args.t_max)
        envs = [g for g in envs if any(c.env == g for c in curves)]
        if not curves:
            raise UsageError(f"--summarise-only: no evaluation logs in {out / 'evals'}")
    else:
        checkpoints = out / "checkpoints" if args.checkpoints else None
        resume = resume_config(args, out, overrides)
        curves = _run(
            lambda: repro_curves.run(
                algos,
                envs,
                args.seeds,
                overrides,
                fan,
                out / "evals",
                checkpoints,
                t_max,
                resume,
                args.seed_group,
            )
        )
        curves = repro_curves.with_other_groups(curves, out / "evals", plan.t_max)
    summary = repro_curves.summarise(curves)
    (out / "curves.json").write_text(json.dumps([c.__dict__ for c in curves]) + "\n")
    plots = []
    for g in envs:
        plots.append(f"{experiment.PLOT_PREFIX}_{env_name(g)}.png")
        repro_curves.plot(curves, g, out / plots[-1], experiment.DIAGNOSTICS)
    if figures is not None:
        plots += figures(curves, envs, out, summary, plan)
    written = [] if tables is None else tables(curves, out, summary, args.bootstrap_reps, SEED)
    best = {g: max_return(g, load_train_config(algos[0], g, [], overrides).env.args) for g in envs}
    scores = curve_scores(curves, best, repro_curves.LAST)
    _write_report(args, f"credit repro {name}", scores, summary, plots)
    write_json(out / "summary.json", summary)
    log.info("repro %s finished in %.0f s", name, time.monotonic() - started)
    for g in envs:
        for a, v in summary[g].items():
            print(
                f"{g:22s} {a:7s} win last10 median {v['median_win_rate_last10']:.2f} "
                f"mean {v['mean_win_rate_last10']:.2f}  steps to 50/80/95% "
                f"{v['steps_to_50']}/{v['steps_to_80']}/{v['steps_to_95']}  smoothed "
                f"{v['steps_to_50_smoothed']}/{v['steps_to_80_smoothed']}/"
                f"{v['steps_to_95_smoothed']}  wall {v['wall_s']:.0f} s"
            )
    if "verdict" in summary:
        print("\n".join(describe(summary["verdict"])))
    files = ["summary.json", *written, "curves.json", "report.html", "evals/", *plots]
    print(f"results in {out}: " + ", ".join(files))
    return 0


def cmd_matrix(args: argparse.Namespace) -> int:
    algos = [a for a in args.algos.split(",") if a]
    games = [g for g in args.games.split(",") if g]
    check_algos(algos)
    for g in games:
        if not g.startswith("matrix/"):
            raise UsageError(
                f"{g!r} is not a matrix game; valid games: {', '.join(repro_matrix.GAMES)}"
            )
    if args.seeds < 1:
        raise UsageError(f"--seeds must be >= 1, got {args.seeds}")
    fan = fan_out_config(args)
    overrides = list(args.set) + ([f"run.t_max={args.t_max}"] if args.t_max else [])
    optimum, t_max, every, pair_t_max = {}, 0, [], {}
    for g in games:  # validates every (algo, game) config before any training starts
        cfgs = [load_train_config(a, g, [], overrides) for a in algos]
        optimum[g] = repro_matrix.optimum_of(g, cfgs[0].env.args)
        t_max += sum(c.run.t_max for c in cfgs)
        every += cfgs
        pair_t_max.update({(g, a): c.run.t_max for a, c in zip(algos, cfgs, strict=True)})
    overrides += seed_group_overrides(args, every)
    out = Path(args.out)
    (out / "evals").mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    if args.summarise_only:
        curves = repro_matrix.load_evals(out / "evals", algos, games)
        games = [g for g in games if any(c.game == g for c in curves)]
        if not curves:
            raise UsageError(f"--summarise-only: no evaluation logs in {out / 'evals'}")
    else:
        resume = resume_config(args, out, overrides)
        curves = _run(
            lambda: repro_matrix.run(
                algos,
                games,
                args.seeds,
                overrides,
                fan,
                out / "evals",
                t_max,
                resume,
                args.seed_group,
            )
        )
        (out / "curves.json").write_text(json.dumps([c.__dict__ for c in curves]) + "\n")
        curves = repro_matrix.with_other_groups(curves, out / "evals", pair_t_max)
    summary = repro_matrix.summarise(curves, optimum)
    plots = [f"matrix_{g.split('/', 1)[1]}.png" for g in games]
    for g, name in zip(games, plots, strict=True):
        repro_matrix.plot(curves, g, out / name)
    _write_report(args, "credit repro matrix", matrix_scores(curves, optimum), summary, plots)
    write_json(out / "summary.json", summary)
    log.info("repro matrix finished in %.0f s", time.monotonic() - started)
    for a in (a for a in algos if a in summary):
        cells = ", ".join(
            f"{g}: {v['optimal_runs']}/{v['runs']} optimal, median {v['final_return_median']:g}"
            for g, v in summary[a].items()
        )
        print(f"{a:8s} {cells}")
    made = "summary.json, " + ("" if args.summarise_only else "curves.json, ")
    print(f"results in {out}: {made}report.html, " + ", ".join(plots))
    return 0


def _write_report(args, title: str, scores, summary: dict, plots: list[str]) -> None:
    """summary["aggregate"], the aggregate figures and report.html (`cluster.repro.report`)."""
    out = Path(args.out)
    figures = [(p, (out / p).read_bytes()) for p in plots]
    repro_report.write_outputs(
        out, f"{title}: {out}", scores, summary, figures, args.bootstrap_reps
    )
