"""Aggregate statistics over seeds and maps, computed with `rliable` (Agarwal et al., "Deep
reinforcement learning at the edge of the statistical precipice", NeurIPS 2021).

Scores are one number per run (seed) of an algorithm on an env, in [0, 1]-ish units:
    win_rate: the run's final test win rate (maps with wins);
    normalised_return: the run's final test return divided by the env's maximum return (the
        matrix games' optimum; on SMAC-like maps `reward_scale_rate`, 20, the return of a
        perfect episode).
What "final" means is the experiment's own (`cluster.repro.curves`: the mean of the last 10
evaluations, as Table 5.2; `cluster.repro.matrix`: the last evaluation).

For every metric `summarise` gives, per env and algorithm (with the runs' scores) and across
envs, the interquartile mean (IQM, `rliable.metrics.aggregate_iqm`) with a stratified
bootstrap confidence interval (`rliable.library.get_interval_estimates`, percentile method),
and for each pair of algorithms the probability of improvement across the envs both ran on
(`rliable.metrics.probability_of_improvement`) with its interval. rliable draws its bootstrap
indices from numpy's global generator, so every interval is computed in its own call, for one
algorithm (or pair), right after `np.random.seed(seed)`: the recorded `reps` and `seed`
reproduce each number with rliable alone (the summary's "bootstrap" entry says how).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

logging.getLogger("absl").setLevel(logging.WARNING)  # rliable logs a line per interval

REPS = 2000  # bootstrap draws per interval
SEED = 0  # numpy global seed set before each interval's draws
CONFIDENCE = 0.95
TAUS = np.linspace(0.0, 1.0, 41)  # thresholds of the performance profiles
LABELS = {"win_rate": "final win rate", "normalised_return": "final return / max return"}

# metric -> env -> algo -> one score per run
Scores = dict[str, dict[str, dict[str, list[float]]]]


def percentile_interval(samples, statistic, reps: int = REPS, seed: int = SEED) -> list[float]:
    """The CONFIDENCE percentile bootstrap interval of `statistic(*samples, axis=-1)`, each
    sample resampled on its own (`scipy.stats.bootstrap`, a numpy generator seeded `seed`).
    The one bootstrap of the Table 5.1 verdict and of Table 5.2."""
    from scipy import stats

    res = stats.bootstrap(
        tuple(np.asarray(x, dtype=float) for x in samples),
        statistic,
        n_resamples=reps,
        confidence_level=CONFIDENCE,
        method="percentile",
        rng=np.random.default_rng(seed),
    )
    return [float(res.confidence_interval.low), float(res.confidence_interval.high)]


def mean(x: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean(x, axis=axis)


def mean_difference(x: np.ndarray, y: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean(x, axis=axis) - np.mean(y, axis=axis)


@contextlib.contextmanager
def _seeded(seed: int) -> Iterator[None]:
    """numpy's global generator seeded for rliable's draws, restored afterwards."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


def interval(
    scores: np.ndarray | list[np.ndarray], func: Callable, reps: int, seed: int
) -> tuple[float, list[float]]:
    """(point estimate, [low, high]) of scalar statistic `func` over `scores` (one
    runs x tasks matrix, or a list of them for a statistic of several algorithms)."""
    from rliable import library

    with _seeded(seed):
        point, ci = library.get_interval_estimates(
            {"x": scores},
            lambda *s: np.array([func(*s)]),
            reps=reps,
            confidence_interval_size=CONFIDENCE,
        )
    return float(point["x"][0]), [float(ci["x"][0][0]), float(ci["x"][1][0])]


def runs_by_tasks(per_env: dict[str, dict[str, list[float]]], algo: str, envs: list[str]):
    """[runs, tasks] matrix of `algo` over `envs`, each env cut to the fewest runs any of
    them has (rliable's stratified bootstrap takes one run count per matrix)."""
    n = min(len(per_env[g][algo]) for g in envs)
    return np.asarray([per_env[g][algo][:n] for g in envs], dtype=float).T


def max_return(env_id: str, env_args: dict) -> float:
    """The return of a perfect episode: a matrix game's optimum; on skirmish and SMAC maps
    (rewards scaled as SMAC does) `reward_scale_rate`."""
    from actors.envs.registry import env_family, make_env

    family = env_family(env_id)  # a map file's is "skirmish"
    if family == "matrix":
        return float(make_env(env_id, seed=0, **env_args).optimal_return)
    if family in ("skirmish", "smac"):
        from actors.envs.skirmish.config import SkirmishConfig

        if not env_args.get("reward_scale", True):
            raise ValueError(f"{env_id}: no maximum return with env.args.reward_scale=false")
        return float(env_args.get("reward_scale_rate", SkirmishConfig.reward_scale_rate))
    raise ValueError(f"{env_id}: no maximum return known for the {family!r} family")


def curve_scores(curves: list, best: dict[str, float], last: int) -> Scores:
    """Scores of `cluster.repro.curves.Curve`s: each seed's mean over its last `last`
    evaluations (win rate; return / best[env])."""
    out: Scores = {"win_rate": {}, "normalised_return": {}}
    for c in curves:
        won = np.asarray(c.won, float)[-last:].mean(0)
        ret = np.asarray(c.returns, float)[-last:].mean(0) / best[c.env]
        out["win_rate"].setdefault(c.env, {})[c.algo] = won.tolist()
        out["normalised_return"].setdefault(c.env, {})[c.algo] = ret.tolist()
    return out


def matrix_scores(curves: list, best: dict[str, float]) -> Scores:
    """Scores of `cluster.repro.matrix.Curve`s: each seed's last return / best[game]."""
    out: Scores = {"normalised_return": {}}
    for c in curves:
        ret = np.asarray(c.returns[-1], float) / best[c.game]
        out["normalised_return"].setdefault(c.game, {})[c.algo] = ret.tolist()
    return out


def summarise(scores: Scores, reps: int = REPS, seed: int = SEED) -> dict:
    """The "aggregate" entry of a reproduction's summary.json (module docstring)."""
    from importlib.metadata import version

    from rliable import metrics

    out: dict = {
        "library": f"rliable {version('rliable')}",
        "bootstrap": {
            "reps": reps,
            "seed": seed,
            "confidence": CONFIDENCE,
            "method": "percentile",
            "recompute": "np.random.seed(seed), then rliable.library.get_interval_estimates("
            "{name: scores}, func, reps=reps) for one algorithm (or one pair) per call; scores "
            "is runs x envs, the envs in the entry's order (sorted), each cut to its first "
            "`runs` runs; func aggregate_iqm, or probability_of_improvement(x, y) on [x, y]",
        },
        "metrics": {},
    }
    for metric, unsorted in scores.items():
        # envs and algorithms sorted: the same columns and pairs however the runs were made
        per_env = {g: unsorted[g] for g in sorted(unsorted)}
        algos = sorted({a for cells in per_env.values() for a in cells})
        entry: dict = {"label": LABELS.get(metric, metric), "per_env": {}, "across_envs": {}}
        for env, cells in per_env.items():
            entry["per_env"][env] = {}
            for algo, runs in cells.items():
                iqm, ci = interval(
                    np.asarray(runs, float)[:, None], metrics.aggregate_iqm, reps, seed
                )
                entry["per_env"][env][algo] = {
                    "iqm": iqm,
                    "ci": ci,
                    "runs": len(runs),
                    "scores": runs,
                }
        for algo in algos:
            envs = [g for g in per_env if algo in per_env[g]]
            m = runs_by_tasks(per_env, algo, envs)
            iqm, ci = interval(m, metrics.aggregate_iqm, reps, seed)
            entry["across_envs"][algo] = {"iqm": iqm, "ci": ci, "envs": envs, "runs": m.shape[0]}
        entry["probability_of_improvement"] = _improvement(per_env, algos, reps, seed)
        out["metrics"][metric] = entry
    return out


def _improvement(per_env: dict, algos: list[str], reps: int, seed: int) -> dict:
    """{"X > Y": {p, ci, envs}} for each pair of algorithms, over the envs both ran on."""
    from rliable import metrics

    pairs = {}
    for i, x in enumerate(algos):
        for y in algos[i + 1 :]:
            envs = [g for g in per_env if x in per_env[g] and y in per_env[g]]
            if not envs:
                continue
            mx, my = runs_by_tasks(per_env, x, envs), runs_by_tasks(per_env, y, envs)
            p, ci = interval([mx, my], metrics.probability_of_improvement, reps, seed)
            runs = [mx.shape[0], my.shape[0]]
            pairs[f"{x} > {y}"] = {"p": p, "ci": ci, "envs": envs, "runs": runs}
    return pairs


def plot(scores: Scores, summary: dict, out: Path, reps: int = REPS, seed: int = SEED) -> list[str]:
    """aggregate_intervals.png (IQM across envs with its interval, per metric) and
    aggregate_profiles.png (performance profiles: the fraction of runs scoring above tau,
    with bootstrap bands) in `out`; returns the file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from rliable import library, plot_utils

    names = list(scores)
    algos = list(dict.fromkeys(a for m in names for a in summary["metrics"][m]["across_envs"]))
    algos = [a for a in algos if all(a in summary["metrics"][m]["across_envs"] for m in names)]
    point = {a: [summary["metrics"][m]["across_envs"][a]["iqm"] for m in names] for a in algos}
    ci = {
        a: np.asarray([summary["metrics"][m]["across_envs"][a]["ci"] for m in names]).T
        for a in algos
    }
    import seaborn as sns

    colors = dict(zip(algos, sns.color_palette("colorblind", n_colors=len(algos)), strict=True))
    fig, _ = plot_utils.plot_interval_estimates(
        point,
        ci,
        [f"IQM {LABELS.get(m, m)}" for m in names],
        algorithms=algos,
        colors=colors,
        xlabel="score",
        row_height=0.6,
        xlabel_y_coordinate=-0.15,
    )
    fig.savefig(out / "aggregate_intervals.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    fig, axes = plt.subplots(1, len(names), figsize=(6 * len(names), 4.2), squeeze=False)
    for ax, metric in zip(axes[0], names, strict=True):
        per_env = {g: scores[metric][g] for g in sorted(scores[metric])}
        mats = {}
        for a in algos:
            envs = [g for g in per_env if a in per_env[g]]
            mats[a] = runs_by_tasks(per_env, a, envs)
        with _seeded(seed):
            prof, prof_ci = library.create_performance_profile(mats, TAUS, reps=reps)
        plot_utils.plot_performance_profiles(
            prof,
            TAUS,
            performance_profile_cis=prof_ci,
            colors=colors,
            ax=ax,
            xlabel=f"{LABELS.get(metric, metric)} (τ)",
        )
        ax.legend(loc="lower left", fontsize="small")
    fig.tight_layout()
    fig.savefig(out / "aggregate_profiles.png", dpi=110)
    plt.close(fig)
    return ["aggregate_intervals.png", "aggregate_profiles.png"]
