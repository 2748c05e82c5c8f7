"""Seed Fig. 5.3 on both matrix games: every algorithm, N seeds trained side by side.

Each (algorithm, game) pair is one seed-batched LocalTrainer (E = seeds); pairs run in a
small process pool or as Ray tasks on a cluster (`cluster.repro.fanout`). Writes
evals/<game>__<algo>.jsonl as each pair evaluates, then summary.json, curves.json and
matrix_<game>.png.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from actors.envs.registry import make_env
from cluster.repro import groups as repro_groups
from cluster.repro.fanout import run_pairs
from cluster.repro.pairs import FanOutConfig, Pair, StatusLine
from cluster.repro.resume import PairJournal, PairStore, ResumeConfig

log = logging.getLogger(__name__)

GAMES = ("matrix/two_step", "matrix/four_game")
ALGOS = ("iql", "vdn", "qmix", "qmix_ns", "rdn")


@dataclass(frozen=True)
class Curve:
    """Test return of every seed at every evaluation: t_env [K], returns [K, seeds]; for RDN,
    what its critic learned (cluster.inspect.rdn_diagnostics), one entry per seed; the code's
    commits it was trained at (two or more if it was resumed at another); the seed groups it
    holds, [{group, seeds, evaluations}] (`cluster.repro.groups`; empty in records made
    before groups existed: group 0)."""

    algo: str
    game: str
    t_env: list[int]
    returns: list[list[float]]
    wall_s: float
    rdn_diagnostics: list[dict] | None = None
    commits: list[str] = field(default_factory=list)
    groups: list[dict] = field(default_factory=list)


def run_pair(
    algo: str,
    game: str,
    seeds: int,
    overrides: list[str],
    resume: ResumeConfig | None = None,
    group: int = 0,
    report: Callable[[str], None] | None = None,
) -> Curve:
    """Train `seeds` seeds of `algo` on `game` in one seed-batched trainer; `report` gets one
    JSON line per evaluation ({env, algo, t_env, returns [seeds], wall_s, commit}); `resume`:
    where it checkpoints and continues from (`cluster.repro.resume`), None for nowhere;
    `group`: its seed group (`cluster.repro.groups`; its run.seed is among `overrides`)."""
    from cluster.config.train import load_train_config
    from cluster.launch.local import LocalTrainer
    from cluster.process import configure

    with PairJournal(resume, Pair(algo, game, group), report) as journal:
        cfg = load_train_config(algo, game, [], overrides + journal.overrides())
        configure(cfg.run)  # the pair's torch threads (run.torch_threads) and seed
        trainer = LocalTrainer(cfg, n_ensemble=seeds)
        journal.attach(trainer)

        def on_eval(records) -> None:
            returns = [r.test_return_mean for r in records]
            journal.add({"env": game, "algo": algo, "t_env": records[0].t_env, "returns": returns})

        trainer.train(on_eval=on_eval)
        if not journal.rows or journal.rows[-1]["t_env"] != trainer.core.t_env:
            on_eval(trainer.core.evaluate())
        journal.finish()
    diagnostics = None
    if algo == "rdn":
        from cluster.inspect.rdn_diagnostics import diagnose

        diagnostics = diagnose(trainer.core.learner, game, cfg.env.args)
    rows = journal.rows
    t_env, returns = [r["t_env"] for r in rows], [r["returns"] for r in rows]
    groups = [{"group": group, "seeds": seeds, "evaluations": len(rows)}]
    return Curve(algo, game, t_env, returns, journal.wall_s, diagnostics, journal.commits, groups)


def load_evals(log_dir: Path, algos: list[str], games: list[str]) -> list[Curve]:
    """Curves rebuilt from the per-pair evaluation logs (pairs without a log are skipped),
    each pair's seed groups merged into one curve (`cluster.repro.groups.merge`); no RDN
    diagnostics: those come from the trained learner, not the log."""
    curves = [load_pair(log_dir, algo, game) for game in games for algo in algos]
    return [c for c in curves if c is not None]


def load_pair(log_dir: Path, algo: str, game: str, finished_at: int | None = None) -> Curve | None:
    """One pair's curve from the logs of all its seed groups (None without a log; with
    `finished_at`, only the groups whose log reaches it: `cluster.repro.groups.load`)."""
    pair = Pair(algo, game)
    loaded = repro_groups.load(log_dir, pair.key, pair.label, finished_at=finished_at)
    if loaded is None:
        return None
    rows, info = loaded
    t_env, returns = [r["t_env"] for r in rows], [r["returns"] for r in rows]
    wall_s = float(rows[-1]["wall_s"])
    return Curve(algo, game, t_env, returns, wall_s, None, info["commits"], info["groups"])


def with_other_groups(
    curves: list[Curve], log_dir: Path, t_max: dict[tuple[str, str], int]
) -> list[Curve]:
    """The curves a run trained, each replaced by the merge of all its pair's finished seed
    groups (from their logs in `log_dir`, without RDN diagnostics: those that reach the pair's
    t_max, `t_max[(game, algo)]`) where other groups have logs; a group still training is
    left out."""
    return repro_groups.with_finished_groups(curves, log_dir, t_max, lambda c: c.game, load_pair)


def summarise(curves: list[Curve], optimum: dict[str, float]) -> dict:
    """{algo: {game: {final_return_median, _q25, _q75, optimal_runs, runs}}}."""
    out: dict = {}
    for c in curves:
        final = np.asarray(c.returns[-1])
        out.setdefault(c.algo, {})[c.game.split("/", 1)[1]] = {
            "final_return_median": float(np.median(final)),
            "final_return_q25": float(np.percentile(final, 25)),
            "final_return_q75": float(np.percentile(final, 75)),
            "optimal_runs": int(np.sum(final >= optimum[c.game] - 1e-3)),
            "runs": len(final),
            "final_returns": [float(x) for x in final],
            "wall_s": round(c.wall_s, 1),
            "commits": c.commits,
            "groups": c.groups or [{"group": 0, "seeds": len(final), "evaluations": len(c.t_env)}],
        }
    return out


def plot(curves: list[Curve], game: str, path: Path) -> None:
    """Median test return with the 25-75 percentile band, one line per algorithm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    for c in (c for c in curves if c.game == game):
        r = np.asarray(c.returns)
        t = np.asarray(c.t_env)
        med = np.median(r, axis=1)
        ax.plot(t, med, label=c.algo)
        ax.fill_between(t, np.percentile(r, 25, axis=1), np.percentile(r, 75, axis=1), alpha=0.2)
    ax.set_xlabel("env steps")
    ax.set_ylabel("test return")
    n = len(curves[0].returns[0]) if curves else 0
    ax.set_title(f"{game}: median of {n} seeds, 25-75 percentile band")
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run(
    algos: list[str],
    games: list[str],
    seeds: int,
    overrides: list[str],
    fan: FanOutConfig,
    log_dir: Path | None = None,
    total_steps: int = 0,
    resume: ResumeConfig | None = None,
    group: int = 0,
) -> list[Curve]:
    """Every (algo, game) pair where `fan` says, as seed group `group` (its run.seed among
    `overrides`; `cluster.repro.groups`); curves in (game, algo) order, evaluations in
    log_dir/<game>__<algo>.jsonl as they happen. With `total_steps` (every pair's t_max
    together), a status line shows the env steps done and each pair's latest median return.
    With `resume` (and its output folder), pairs checkpoint, continue from their checkpoints
    and are skipped when already finished (`cluster.repro.resume`)."""
    pairs = [Pair(a, g, group) for g in games for a in algos]
    status = StatusLine(total_steps, "returns", "return") if total_steps else None
    store = None
    if resume is not None and resume.out is not None:
        store = PairStore(resume, lambda c: dict(c.__dict__), lambda d: Curve(**d))
    args = (seeds, overrides, resume, group)
    return run_pairs(run_pair, pairs, args, fan, log_dir, None, status, store)


def optimum_of(game: str, env_args: dict) -> float:
    return make_env(game, seed=0, **env_args).optimal_return
