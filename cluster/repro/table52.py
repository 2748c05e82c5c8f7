"""Table 5.2 of Singh, "Improving central value functions for cooperative multi-agent
reinforcement learning" (MSc dissertation, University of the Witwatersrand, 2022) beside ours,
and its ordering claims answered from the runs (`credit repro emcac`'s summary.json "table52"
entry and OUT/table52.md, `cluster.repro.table52_md`).

A cell is one (map, algorithm) pair: each seed's mean test win rate over its last LAST
evaluations (`cluster.repro.curves.final_per_seed`, as the summary's median/mean_win_rate_last10),
then over seeds the median and the mean (the table's two numbers), the 25-75 percentile range
and a bootstrap 95% interval of the mean (`bootstrap`). A pair is matched to a map by its env's
name (`skirmish/3s5z` and `smac/3s5z` -> 3s5z; map files never match: they are not SMAC's maps).

Claims (CLAIMS), each a set of comparisons of two cells' seed means, d = mean(A) - mean(B)
with a bootstrap 95% interval [lo, hi] over both cells' seeds (resampled independently):
    "ge" (A >= B): holds if lo >= 0 (so two cells at the same constant, e.g. both always
        winning, hold); does not hold if hi < 0; else inconclusive.
    "close" (A within CLOSE of B): holds if -CLOSE <= lo and hi <= CLOSE; does not hold if
        lo > CLOSE or hi < -CLOSE; else inconclusive.
A comparison with a cell not run is missing; one with a cell of a single seed (no interval)
is inconclusive. A claim does not hold if any of its comparisons does not; else it is missing
(not yet answerable: the cells are named) if any is missing; else inconclusive if any is;
else it holds. Cells under MIN_STEPS env steps (still running, or cut short) count as they
are, and each claim names those it used (under_min_steps).
"""

from __future__ import annotations

import numpy as np

from actors.envs.registry import env_name, is_map_file
from cluster.errors import UsageError
from cluster.repro import aggregate
from cluster.repro.aggregate import CONFIDENCE
from cluster.repro.curves import LAST, Curve, final_per_seed

SOURCE = (
    'Singh, "Improving central value functions for cooperative multi-agent reinforcement '
    'learning", MSc dissertation, University of the Witwatersrand, 2022, Table 5.2'
)
MAPS = ("MMM2", "2c_vs_64zg", "3s5z", "1c3s5z")
ALGOS = ("cac", "ecac", "emcac", "coma", "qmix")
NAMES = {"cac": "CAC", "ecac": "E-CAC", "emcac": "EM-CAC", "coma": "COMA", "qmix": "QMIX"}
# Table 5.2 as printed, "median/mean" test win rate (%) over the last 10 evaluations after
# 2M env steps; 1c3s5z's COMA cell prints one number, without saying which.
DISSERTATION = {
    "MMM2": {"cac": "29/35", "ecac": "43/55", "emcac": "62/65", "coma": "0/0", "qmix": "64/70"},
    "2c_vs_64zg": {
        "cac": "97/100",
        "ecac": "95/100",
        "emcac": "97/100",
        "coma": "15/20",
        "qmix": "97/100",
    },
    "3s5z": {"cac": "15/5", "ecac": "48/63", "emcac": "93/93", "coma": "1/0", "qmix": "85/90"},
    "1c3s5z": {"cac": "89/90", "ecac": "95/100", "emcac": "98/100", "coma": "30", "qmix": "94/95"},
}
DISSERTATION_STEPS = 2_000_000
MIN_STEPS = 1_000_000  # the env steps a cell needs to count as a full run (issue 37)
CLOSE = 0.10  # "close": within 10 win-rate points (the table's own EM-CAC/QMIX pairs: <= 8)
EPS = 1e-9  # float slack of the interval tests (two means of equal seeds differ by ~1e-16)
_CHAIN = (("emcac", "ecac"), ("ecac", "cac"))
CLAIMS = (
    {
        "claim": "EM-CAC >= E-CAC >= CAC on MMM2 and 3s5z",
        "tests": [("ge", a, b, m) for m in ("MMM2", "3s5z") for a, b in _CHAIN],
    },
    {
        "claim": f"EM-CAC close to QMIX (within {100 * CLOSE:.0f} points) on all four maps",
        "tests": [("close", "emcac", "qmix", m) for m in MAPS],
    },
    {
        "claim": "COMA lowest on every map",
        "tests": [("ge", a, "coma", m) for m in MAPS for a in ALGOS if a != "coma"],
    },
)


def printed_pair(text: str) -> tuple[float | None, float | None]:
    """A printed dissertation cell as (median, mean) in [0, 1]; (None, None) when it prints
    one number (which of the two it is is not said)."""
    parts = text.split("/")
    if len(parts) != 2:
        return None, None
    return float(parts[0]) / 100, float(parts[1]) / 100


def impossible_cells() -> list[str]:
    """Dissertation cells whose median and mean cannot both hold for win rates in [0, 1]: a
    mean of 1 needs every seed at 1 (so the median is 1), a mean of 0 every seed at 0."""
    bad = []
    for m, row in DISSERTATION.items():
        for a, text in row.items():
            med, mean = printed_pair(text)
            if mean is not None and mean in (0.0, 1.0) and med != mean:
                bad.append(f"{m} {NAMES[a]} {text}")
    return bad


def bootstrap(samples: list[np.ndarray], statistic, reps: int, seed: int) -> list[float] | None:
    """`aggregate.percentile_interval`, or None when a sample has fewer than 2 values."""
    if any(len(x) < 2 for x in samples):
        return None
    return aggregate.percentile_interval(samples, statistic, reps, seed)


def cell(c: Curve, reps: int, seed: int) -> dict:
    """One pair's Table 5.2 cell (module docstring); win rates in [0, 1]."""
    per_seed = final_per_seed(c.won)
    kl = [d["kl_masked_fraction"] for d in c.learner[-LAST:] if "kl_masked_fraction" in d]
    return {
        "env": c.env,
        "median": float(np.median(per_seed)),
        "mean": float(np.mean(per_seed)),
        "per_seed": per_seed.tolist(),
        "iqr": [float(np.percentile(per_seed, 25)), float(np.percentile(per_seed, 75))],
        "ci_mean": bootstrap([per_seed], aggregate.mean, reps, seed),
        "seeds": int(per_seed.size),
        "t_env": int(c.t_env[-1]),
        "evaluations": len(c.t_env),
        "last_evaluations": min(LAST, len(c.t_env)),
        # the learner logs it per evaluation as a mean over seeds (and over its updates)
        "kl_masked_fraction": float(np.mean(kl)) if kl else None,
        "commits": c.commits,
        "groups": c.groups,
    }


def table_map(env: str) -> str | None:
    """The Table 5.2 map an env id is (module docstring), or None."""
    name = None if is_map_file(env) else env_name(env)
    return name if name in MAPS else None


def check_envs(envs: list[str]) -> None:
    """Raise UsageError if two of `envs` are one Table 5.2 map (its cell would be ambiguous);
    `credit repro emcac` checks its --envs before anything trains."""
    seen: dict[str, str] = {}
    for g in envs:
        m = table_map(g)
        if m in seen:
            raise UsageError(
                f"Table 5.2: {seen[m]} and {g} are both {m}; run or summarise one of them "
                "per --out (--envs)"
            )
        if m is not None:
            seen[m] = g


def cells_of(curves: list[Curve], reps: int, seed: int) -> dict[str, dict[str, dict | None]]:
    """{map: {algo: cell, or None when not run}} over MAPS x ALGOS."""
    check_envs(list(dict.fromkeys(c.env for c in curves)))
    found = {(table_map(c.env), c.algo): c for c in curves}
    return {
        m: {a: cell(found[m, a], reps, seed) if (m, a) in found else None for a in ALGOS}
        for m in MAPS
    }


def compare(relation: str, a: dict | None, b: dict | None, reps: int, seed: int) -> dict:
    """One comparison of cells a and b: {difference, interval, verdict} (module docstring)."""
    if a is None or b is None:
        return {"difference": None, "interval": None, "verdict": "missing"}
    x, y = np.asarray(a["per_seed"]), np.asarray(b["per_seed"])
    d = float(x.mean() - y.mean())
    ci = bootstrap([x, y], aggregate.mean_difference, reps, seed)
    if ci is None:
        verdict = "inconclusive"
    elif relation == "ge":
        verdict = "holds" if ci[0] >= -EPS else "does not hold" if ci[1] < -EPS else "inconclusive"
    elif ci[0] >= -CLOSE - EPS and ci[1] <= CLOSE + EPS:
        verdict = "holds"
    elif ci[0] > CLOSE + EPS or ci[1] < -CLOSE - EPS:
        verdict = "does not hold"
    else:
        verdict = "inconclusive"
    return {"difference": d, "interval": ci, "verdict": verdict}


def claim_verdict(verdicts: list[str]) -> str:
    """A claim's verdict from its comparisons' (module docstring)."""
    for v in ("does not hold", "missing", "inconclusive"):
        if v in verdicts:
            return v
    return "holds"


def claims(cells: dict, reps: int, seed: int) -> list[dict]:
    """Every claim of CLAIMS answered from `cells` (`cells_of`)."""
    out = []
    for spec in CLAIMS:
        tests = []
        for relation, a, b, m in spec["tests"]:
            got = compare(relation, cells[m][a], cells[m][b], reps, seed)
            tests.append({"map": m, "a": a, "b": b, "relation": relation, **got})
        pairs = {(t["map"], x) for t in tests for x in (t["a"], t["b"])}
        missing = sorted(f"{m} {NAMES[x]}" for m, x in pairs if cells[m][x] is None)
        short = sorted(
            f"{m} {NAMES[x]}"
            for m, x in pairs
            if cells[m][x] is not None and cells[m][x]["t_env"] < MIN_STEPS
        )
        verdict = claim_verdict([t["verdict"] for t in tests])
        out.append(
            {
                "claim": spec["claim"],
                "verdict": verdict,
                "missing": missing,
                "under_min_steps": short,
                "tests": tests,
            }
        )
    return out


def table52(curves: list[Curve], reps: int, seed: int) -> dict:
    """The summary's "table52" entry: the cells, the dissertation's numbers and the claims."""
    cells = cells_of(curves, reps, seed)
    return {
        "source": SOURCE,
        "definition": f"per seed: mean test win rate over its last {LAST} evaluations; per "
        "cell: the median and mean of those over seeds, their 25-75 percentile range (iqr) and "
        f"a percentile bootstrap {CONFIDENCE:.0%} interval of the mean (ci_mean; None under 2 "
        "seeds); win rates in [0, 1]; kl_masked_fraction: the mean of the logged fraction "
        f"(itself a mean over seeds) over the last {LAST} evaluations, None if not logged",
        "bootstrap": {
            "library": "scipy.stats.bootstrap",
            "method": "percentile",
            "reps": reps,
            "seed": seed,
            "confidence": CONFIDENCE,
            "recompute": "scipy.stats.bootstrap(samples, statistic, n_resamples=reps, "
            "confidence_level=confidence, method='percentile', paired=False, vectorized=True, "
            "rng=numpy.random.default_rng(seed)); a cell's ci_mean: samples (per_seed,), "
            "statistic the mean; a comparison's interval: samples (A's per_seed, B's), "
            "statistic mean(A) - mean(B)",
        },
        "rules": {
            "ge": "A >= B holds if the interval of mean(A) - mean(B) has lo >= 0, does not hold "
            "if hi < 0, else inconclusive",
            "close": f"A close to B holds if that interval lies in [-{CLOSE}, {CLOSE}], does not "
            "hold if it lies wholly outside it, else inconclusive",
            "cells": "a comparison with a cell not run is missing; with a cell of one seed (no "
            f"interval) inconclusive; cells under {MIN_STEPS} env steps count as they are "
            "(each claim's under_min_steps names them)",
            "claim": "does not hold if any comparison does not; else missing if any cell is not "
            "run; else inconclusive if any comparison is; else holds",
        },
        "dissertation": DISSERTATION,
        "dissertation_steps": DISSERTATION_STEPS,
        "dissertation_impossible_cells": impossible_cells(),
        "cells": cells,
        "claims": claims(cells, reps, seed),
    }
