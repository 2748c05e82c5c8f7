"""The dissertation's three statements on redundant agents (Section 5.4.2, Table 5.1), answered
from the pairs of `credit repro redundancy` that have finished: RDN's final win rate is flat in
the number of allied zerglings, VDN's and QMIX's fall as zerglings are added, and QMIX without
the state beats QMIX on bane_med and bane_no_z.

A pair (map, algorithm) has finished when its evaluations reach the env steps it was to run
(`Plan`) with the seeds it was to run (a pair whose seed groups have not all run, say 2 of
3, counts as missing); a pair with fewer than two seeds has no interval and counts as
missing. Every interval is a percentile bootstrap (`scipy.stats.bootstrap`, `aggregate.REPS`
draws, each interval drawn by its own `numpy.random.default_rng(seed)`, so the same logs give
the same numbers):

* final: per map and algorithm, each seed's final win rate (its mean over the last 10
  evaluations) and the mean over seeds with its interval;
* slope: per algorithm with finished pairs on maps of at least two zergling counts, the
  least-squares slope of final win rate against allied zerglings over every seed's point,
  its interval resampling seeds within each map (stratified: one sample per map); `flat` when
  the interval lies within +-TOLERANCE win rate per zergling, `falls` when it lies below 0,
  `rises` when above;
* qmix_ns_minus_qmix: on bane_med and bane_no_z, QMIX-nostate's mean final win rate minus
  QMIX's, its interval resampling each algorithm's seeds apart; `beats` when the interval lies
  above 0; beside it rliable's probability of improvement P(qmix_ns > qmix) with its interval
  (`cluster.repro.aggregate.interval`).

A statement answers "yes", "no" or "undecided" only when every pair it wants has finished;
until then it answers "not yet" and lists the pairs missing ({env, algo, why}), with, where
the finished pairs already give an interval, that interval and what it reads as so far
(`so_far`). The maps a slope wants are Table 5.1's and those the run planned; an
answered slope lists the ones still missing beside its number.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from actors.envs.registry import env_name
from cluster.repro import aggregate
from cluster.repro.curves import LAST, Curve, final_per_seed

TOLERANCE = 0.01  # win rate per zergling: a slope whose interval lies within +- this is flat
MIN_SEEDS = 2  # a bootstrap interval needs two seeds of a pair
SLOPES = ("rdn", "vdn", "qmix")  # the statements' algorithms: always given a slope entry
NOSTATE = ("qmix_ns", "qmix")  # QMIX-nostate against QMIX
NOSTATE_ENVS = ("skirmish/bane_med", "skirmish/bane_no_z")
FIGURE = "redundancy_final_vs_zerglings.png"
RULES = {  # statement -> (yes, no) from its interval [lo, hi]; neither: "undecided"
    "flat": (
        lambda lo, hi: lo >= -TOLERANCE and hi <= TOLERANCE,
        lambda lo, hi: hi < -TOLERANCE or lo > TOLERANCE,
    ),
    "falls": (lambda lo, hi: hi < 0, lambda lo, hi: lo >= 0),
    "beats": (lambda lo, hi: lo > 0, lambda lo, hi: hi <= 0),
}


@dataclass(frozen=True)
class Plan:
    """What the run set out to do: each (env, algo) pair's env steps (run.t_max); the
    bootstrap's draws and seed; `seeds`, the seeds every pair is to have (the summary's
    `--seeds`; 0: any number)."""

    t_max: dict[tuple[str, str], int]
    reps: int = aggregate.REPS
    seed: int = aggregate.SEED
    seeds: int = 0

    @classmethod
    def of_curves(cls, curves: list[Curve], reps: int = aggregate.REPS) -> Plan:
        """Every curve taken as finished where it ends."""
        return cls({(c.env, c.algo): int(c.t_env[-1]) for c in curves}, reps)


def verdict(curves: list[Curve], plan: Plan, table_envs: tuple[str, ...]) -> dict:
    """The summary's "verdict" entry (module docstring); `table_envs`: Table 5.1's maps."""
    from cluster.repro.redundancy import ALGOS, ordered, zerglings_of

    done, why = _pairs(curves, plan)
    planned = {a for _, a in plan.t_max}
    algos = [a for a in ALGOS if a in planned or a in SLOPES]
    algos += sorted(planned - set(algos))
    lings = {g: zerglings_of(g) for g in {*table_envs, *(g for g, _ in plan.t_max)}}
    maps = ordered([g for g, n in lings.items() if n is not None])
    final = {}
    for env in ordered(list({g for g, _ in done})):
        final[env] = {a: _final(done[env, a], lings.get(env), plan) for g, a in done if g == env}
    slopes = {a: _slope(a, maps, lings, final, why, plan) for a in algos}
    nostate = {g: _nostate(g, final, why, plan) for g in NOSTATE_ENVS}
    return {
        "bootstrap": _bootstrap(plan),
        "tolerance": TOLERANCE,
        "last_evaluations": LAST,
        "finished": [{"env": g, "algo": a, "t_env": int(done[g, a].t_env[-1])} for g, a in done],
        "missing": [{"env": g, "algo": a, "why": w} for (g, a), w in why.items()],
        "final": final,
        "slope": slopes,
        "qmix_ns_minus_qmix": nostate,
        "statements": _statements(slopes, nostate),
    }


def _pairs(curves: list[Curve], plan: Plan) -> tuple[dict, dict]:
    """({(env, algo): curve} of the finished pairs, {(env, algo): why} of the planned rest)."""
    done, why = {}, {}
    got = {(c.env, c.algo): c for c in curves}
    for key, t_max in plan.t_max.items():
        c = got.get(key)
        if c is None:
            why[key] = "no evaluation log"
        elif c.t_env[-1] < t_max:
            why[key] = f"unfinished: {c.t_env[-1]} of {t_max} env steps"
        elif len(c.won[0]) < MIN_SEEDS:
            why[key] = f"{len(c.won[0])} seed (an interval needs {MIN_SEEDS})"
        elif len(c.won[0]) < plan.seeds:
            why[key] = f"{len(c.won[0])} of {plan.seeds} seeds"
        else:
            done[key] = c
    return done, why


def _missing(pairs: list[tuple[str, str]], final: dict, why: dict) -> list[dict]:
    """{env, algo, why} of each pair in `pairs` that has not finished."""
    return [
        {"env": g, "algo": a, "why": why.get((g, a), "not in this run's --envs or --algos")}
        for g, a in pairs
        if a not in final.get(g, {})
    ]


def _bootstrap(plan: Plan) -> dict:
    from importlib.metadata import version

    return {
        "library": f"scipy {version('scipy')}, rliable {version('rliable')}",
        "reps": plan.reps,
        "seed": plan.seed,
        "confidence": aggregate.CONFIDENCE,
        "method": "percentile",
        "recompute": "scipy.stats.bootstrap(samples, statistic, n_resamples=reps, "
        "method='percentile', rng=numpy.random.default_rng(seed)) per interval; samples: a "
        "pair's per_seed (mean), one per map in the slope's maps order (slope), [qmix_ns, "
        "qmix] (difference of means); P(qmix_ns > qmix) as the aggregate entry says",
    }


def bootstrap_interval(samples: tuple, statistic, plan: Plan) -> tuple[float, list[float]]:
    """(statistic of `samples`, its percentile bootstrap interval, each sample resampled
    apart) with `plan`'s draws and seed."""
    ci = aggregate.percentile_interval(samples, statistic, plan.reps, plan.seed)
    return _r(statistic(*samples, axis=-1)), [_r(v) for v in ci]


def _r(v) -> float:
    return round(float(v), 4)


def _final(c: Curve, zerglings: int | None, plan: Plan) -> dict:
    seeds = [_r(v) for v in final_per_seed(c.won)]  # as recorded: intervals recompute from them
    mean, ci = bootstrap_interval((seeds,), aggregate.mean, plan)
    return {"zerglings": zerglings, "per_seed": seeds, "mean": mean, "ci": ci}


def slope_statistic(x: list[float]):
    """The least-squares slope over every seed's point, samples[i] holding map i's seeds
    (x[i] zerglings), vectorised over leading axes for `scipy.stats.bootstrap`."""

    def stat(*samples, axis=-1):
        ys = [np.moveaxis(np.asarray(s, dtype=float), axis, -1) for s in samples]
        xs = np.repeat(np.asarray(x, dtype=float), [y.shape[-1] for y in ys])
        y = np.concatenate(ys, axis=-1)
        xc = xs - xs.mean()
        return ((y - y.mean(axis=-1, keepdims=True)) * xc).sum(axis=-1) / (xc**2).sum()

    return stat


def _slope(algo: str, maps: list[str], lings: dict, final: dict, why: dict, plan: Plan) -> dict:
    """The slope entry of one algorithm (module docstring)."""
    have = [g for g in maps if algo in final.get(g, {})]
    missing = _missing([(g, algo) for g in maps], final, why)
    x = [lings[g] for g in have]
    out: dict = {"maps": have, "zerglings": x}
    out["per_seed"] = [final[g][algo]["per_seed"] for g in have]
    if len(set(x)) < 2:
        return {**out, "missing": missing, "needs": "finished pairs on two zergling counts"}
    slope, ci = bootstrap_interval(tuple(out["per_seed"]), slope_statistic(x), plan)
    trend = {"flat": RULES["flat"][0](*ci), "falls": RULES["falls"][0](*ci), "rises": ci[0] > 0}
    return {**out, "slope": slope, "ci": ci, **trend, "missing": missing}


def _nostate(env: str, final: dict, why: dict, plan: Plan) -> dict:
    """QMIX-nostate minus QMIX on `env` (module docstring)."""
    from rliable import metrics

    missing = _missing([(env, a) for a in NOSTATE], final, why)
    if missing:
        return {"missing": missing}
    ns, q = (final[env][a]["per_seed"] for a in NOSTATE)
    diff, ci = bootstrap_interval((ns, q), aggregate.mean_difference, plan)
    m = [np.asarray(s, dtype=float)[:, None] for s in (ns, q)]
    p, p_ci = aggregate.interval(m, metrics.probability_of_improvement, plan.reps, plan.seed)
    out = {"qmix_ns": ns, "qmix": q, "difference": diff, "ci": ci, "beats": RULES["beats"][0](*ci)}
    return {**out, "p_qmix_ns_better": _r(p), "p_ci": [_r(v) for v in p_ci]}


def _statements(slopes: dict, nostate: dict) -> dict:
    """The three statements, each "yes", "no" (the interval lies outside the statement's
    range), "undecided" (it straddles the range's edge) or "not yet" (pairs missing), with
    its interval and the pairs still missing."""

    def answer(entry: dict, rule: str) -> dict:
        missing = entry.get("missing", [])
        if "ci" not in entry:
            return {"answer": "not yet", "missing": missing}
        yes, no = RULES[rule]
        said = "yes" if yes(*entry["ci"]) else "no" if no(*entry["ci"]) else "undecided"
        if missing:  # the finished pairs' reading, which the missing ones may change
            return {"answer": "not yet", "so_far": said, "ci": entry["ci"], "missing": missing}
        return {"answer": said, "ci": entry["ci"], "missing": missing}

    out = {"rdn_flat": answer(slopes["rdn"], "flat")}
    out["vdn_falls"] = answer(slopes["vdn"], "falls")
    out["qmix_falls"] = answer(slopes["qmix"], "falls")
    out["qmix_ns_beats_qmix"] = {g: answer(v, "beats") for g, v in nostate.items()}
    return out


def describe(v: dict) -> list[str]:
    """The verdict as printed lines."""
    bs = v["bootstrap"]
    lines = [f"verdict ({bs['confidence']:.0%} percentile bootstrap, {bs['reps']} draws):"]
    for env, cells in v["final"].items():
        for algo, c in cells.items():
            seeds = "/".join(f"{s:g}" for s in c["per_seed"])
            lines.append(f"  final {env} {algo}: {_ci(c['mean'], c['ci'])} (seeds {seeds})")
    for algo, s in v["slope"].items():
        if "slope" in s:
            pairs = zip(s["maps"], s["zerglings"], strict=True)
            over = ", ".join(f"{env_name(g)} ({n})" for g, n in pairs)
            trend = [k for k in ("flat", "falls", "rises") if s[k]] or ["neither"]
            line = f"{_ci(s['slope'], s['ci'])} per zergling over {over}: {', '.join(trend)}"
        else:
            line = "missing " + _pairs_text(s["missing"])
        lines.append(f"  slope {algo}: {line}")
    for env, d in v["qmix_ns_minus_qmix"].items():
        if "missing" in d:
            line = "missing " + _pairs_text(d["missing"])
        else:
            p = _ci(d["p_qmix_ns_better"], d["p_ci"])
            line = f"{_ci(d['difference'], d['ci'])}, P(qmix_ns > qmix) {p}"
        lines.append(f"  qmix_ns - qmix on {env}: {line}")
    for key, s in v["statements"].items():
        cells = s.items() if key == "qmix_ns_beats_qmix" else [("", s)]
        for env, a in cells:
            lines.append(f"  {key} {env}".rstrip() + f": {_answer(a)}")
    return lines


def _ci(x: float, ci: list[float]) -> str:
    return f"{x:.3f} [{ci[0]:.3f}, {ci[1]:.3f}]"


def _pairs_text(missing: list[dict]) -> str:
    return "; ".join(f"{m['env']} {m['algo']} ({m['why']})" for m in missing)


def _answer(a: dict) -> str:
    n = len(a["missing"])
    missing = f"{n} pair{'' if n == 1 else 's'} missing"
    if "ci" not in a:
        return f"not yet ({missing})"
    ci = f"[{a['ci'][0]:.3f}, {a['ci'][1]:.3f}]"
    if a["answer"] == "not yet":
        return f"not yet ({missing}; {a['so_far']} {ci} from the finished pairs)"
    return f"{a['answer']} {ci}"


def plot(v: dict, enemy: str | None, path: Path) -> None:
    """Final win rate against allied zerglings, one panel per algorithm with a finished
    pair: each seed a point, the mean with its bootstrap interval as bars, the fitted slope
    as a line (labelled with its interval)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    algos = [a for a in v["slope"] if v["slope"][a]["maps"]]
    n = max(len(algos), 1)
    fig, axes = plt.subplots(1, n, figsize=(3.8 * n, 4.2), squeeze=False, sharex=True, sharey=True)
    counts = [x for a in algos for x in v["slope"][a]["zerglings"]] or [0]
    span = max(max(counts) - min(counts), 4)
    for ax, algo in zip(axes[0], algos, strict=False):
        _panel(ax, algo, v, 0.02 * span)
    if not algos:
        axes[0][0].text(0.5, 0.5, "no finished pair", ha="center", transform=axes[0][0].transAxes)
    for ax in axes[0]:
        ax.set_xlabel("allied zerglings")
        ax.grid(alpha=0.3)
    axes[0][0].set_xlim(min(counts) - 0.08 * span, max(counts) + 0.08 * span)
    axes[0][0].set_ylabel(f"final win rate (last {LAST} evaluations)")
    axes[0][0].set_ylim(-0.02, 1.02)
    against = f" (the enemy: {enemy})" if enemy else ""
    fig.suptitle(
        f"final win rate against allied zerglings{against}, finished pairs:\nseeds (circles), "
        f"mean with bootstrap {v['bootstrap']['confidence']:.0%} interval (squares), "
        "least-squares slope (line)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _panel(ax, algo: str, v: dict, jitter: float) -> None:
    """One algorithm's seeds, means and slope line on `ax`."""
    s = v["slope"][algo]
    x = np.asarray(s["zerglings"], dtype=float)
    for xi, g in zip(x, s["maps"], strict=True):
        c = v["final"][g][algo]
        dx = np.linspace(-jitter, jitter, len(c["per_seed"]))
        ax.plot(xi + dx, c["per_seed"], "o", color="0.5", ms=4, mfc="none")
        yerr = [[c["mean"] - c["ci"][0]], [c["ci"][1] - c["mean"]]]
        ax.errorbar([xi], [c["mean"]], yerr=yerr, fmt="s", color="C0", capsize=4)
    if "slope" not in s:
        ax.set_title(f"{algo}: no slope yet (one zergling count)", fontsize=9)
        return
    xs = np.array([x.min(), x.max()])
    ys = np.mean(np.concatenate(s["per_seed"])) + s["slope"] * (xs - _seed_x_mean(s))
    ax.plot(xs, ys, "-", color="C3", label=f"slope {_ci(s['slope'], s['ci'])}/zergling")
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title(algo)


def _seed_x_mean(s: dict) -> float:
    """The mean zergling count over every seed's point (where the fitted line passes
    through the mean win rate)."""
    points = zip(s["zerglings"], s["per_seed"], strict=True)
    return float(np.mean([x for x, seeds in points for _ in seeds]))
