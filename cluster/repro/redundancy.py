"""The dissertation's redundancy experiment (Section 5.4.2, Table 5.1, Figs. 5.6-5.9): RDN, VDN,
QMIX, QMIX-nostate and IQL on bane_vs_bane and its variants with fewer (or more) allied zerglings,
the enemy always 20 zerglings and 4 banelings.

Runs, logs and the per-map plots are `cluster.repro.curves`' (`credit repro redundancy`); this
module names the maps and algorithms, turns `--zerglings 0,5,...` into generated maps
(`skirmish/bane_z<N>`), and draws the dissertation's figures over all maps at once. A map
file a user wrote (`--envs path/to/map.yaml`) takes part like a built-in map: named by its
file stem in titles and plot names, and by its allied zerglings on the final chart (a map
whose units are drawn every episode has no such number and stays off that chart).

* redundancy_median.png (Fig. 5.6): per map, the median win rate over seeds with the 25-75%
  band, one line per algorithm;
* redundancy_variance.png (Fig. 5.7): the variance of the win rate across seeds;
* redundancy_p75.png, redundancy_p25.png (Figs. 5.8, 5.9): the 75th and 25th percentiles;
* redundancy_final.png (not in the dissertation): the final win rate (each seed's mean over its last
  10 evaluations; median and 25-75% over seeds) against the number of allied zerglings, a
  line through the Table 5.1 maps, open squares for the generated ones and open diamonds
  for map files; beside it the final return the same way;
* redundancy_final_vs_zerglings.png: the verdict's view of the same axis (`cluster.repro.verdict`),
  finished pairs only: every seed a point, the mean with its bootstrap interval, the fitted
  slope per algorithm.

Maps are ordered from the most redundant zerglings to the fewest, as in the dissertation's figures.
`summary.json` gets a "redundancy" entry with every number these figures draw, and a
"verdict" entry with the dissertation's three statements (`cluster.repro.verdict`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from actors.envs.registry import env_name, is_map_file
from actors.envs.skirmish import example_map_file
from actors.envs.skirmish.maps import BANE_VARIANT, BANE_VARIANT_MAX, builtin_map, load_map_file
from actors.envs.skirmish.spec import MapSpec
from cluster.errors import UsageError
from cluster.repro import smac as repro_smac
from cluster.repro import verdict as repro_verdict
from cluster.repro.curves import LAST, Curve, final_per_seed

ENVS = (
    "skirmish/bane_vs_bane",
    "skirmish/bane_med",
    "skirmish/bane_small",
    "skirmish/bane_no_z",
)
ALGOS = ("rdn", "vdn", "qmix", "qmix_ns", "iql")
PLOT_PREFIX = "redundancy"
DIAGNOSTICS = repro_smac.DIAGNOSTICS  # the per-map plots: Q scale and TD losses
STATS = {  # file suffix -> (panel y label, statistic over seeds at each evaluation)
    "median": ("median win rate (25-75% band)", lambda w: np.median(w, axis=1)),
    "variance": ("variance of the win rate across seeds", lambda w: np.var(w, axis=1)),
    "p75": ("75th percentile win rate", lambda w: np.percentile(w, 75, axis=1)),
    "p25": ("25th percentile win rate", lambda w: np.percentile(w, 25, axis=1)),
}
LINE_STATS = {"median": 50, "p25": 25, "p75": 75}  # final chart: key -> percentile over seeds


def zergling_envs(spec: str) -> list[str]:
    """`--zerglings 0,5,10` -> ["skirmish/bane_z0", "skirmish/bane_z5", "skirmish/bane_z10"]."""
    out = []
    for n in (x.strip() for x in spec.split(",")):
        if not n:
            continue
        if not n.isdigit() or int(n) > BANE_VARIANT_MAX:
            raise UsageError(
                f"--zerglings takes whole numbers 0..{BANE_VARIANT_MAX} separated by commas, "
                f"got {n!r}"
            )
        out.append(f"skirmish/bane_z{int(n)}")
    return out


def map_of(env: str) -> MapSpec | None:
    """The skirmish map of `env` (a built-in, a generated bane_z<N>, a user's map file, or
    skirmish/custom's example map), or None for an env of another family."""
    if is_map_file(env):
        return load_map_file(env)
    family, _, name = env.partition("/")
    if family != "skirmish":
        return None
    return load_map_file(example_map_file()) if name == "custom" else builtin_map(name)


def zerglings_of(env: str) -> int | None:
    """Allied zerglings of a skirmish map, or None where the map does not fix them (units
    drawn every episode, or not a skirmish map): such maps stay off the final chart."""
    spec = map_of(env)
    if spec is None or spec.team_gen is not None:
        return None
    return sum(g.count for g in spec.allies if g.type == "zergling")


def enemy_of(env: str) -> str | None:
    """The enemy team of a fixed skirmish map, e.g. "20 zerglings + 4 banelings"."""
    spec = map_of(env)
    if spec is None or spec.team_gen is not None:
        return None
    return " + ".join(f"{g.count} {g.type}s" for g in spec.enemies)


def generated(env: str) -> bool:
    """A map of `--zerglings` (`skirmish/bane_z<N>`), not one of Table 5.1's files."""
    return not is_map_file(env) and BANE_VARIANT.fullmatch(env.partition("/")[2]) is not None


def ordered(envs: list[str]) -> list[str]:
    """Most allied zerglings first (the dissertation's left-to-right order), maps without a
    fixed number last; ties keep their order."""

    def rank(env: str) -> int:
        n = zerglings_of(env)
        return -1 if n is None else n

    return sorted(envs, key=lambda g: -rank(g))


def curve_stats(c: Curve) -> dict:
    """The numbers behind Figs. 5.6-5.9 for one (env, algo): each statistic at each
    evaluation."""
    w = np.asarray(c.won, dtype=float)
    out = {"t_env": list(c.t_env), "seeds": int(w.shape[1])}
    for key, (_, stat) in STATS.items():
        out[key] = [round(float(v), 4) for v in stat(w)]
    return out


def final_stats(curves: list[Curve], envs: list[str]) -> dict:
    """Per algo, against the number of zerglings: each seed's mean win rate over its last
    LAST evaluations, and their median and 25th / 75th percentiles over seeds; the same for
    the return under `return_*` (it separates the algorithms while none wins yet)."""
    out: dict = {}
    for env in ordered(envs):
        if zerglings_of(env) is None:
            continue
        for c in curves:
            if c.env != env:
                continue
            empty: dict = {"env": [], "generated": [], "map_file": [], "zerglings": []}
            cell = out.setdefault(c.algo, empty)
            cell["env"].append(env)
            cell["generated"].append(generated(env))
            cell["map_file"].append(is_map_file(env))
            cell["zerglings"].append(zerglings_of(env))
            for prefix, values in (("", c.won), ("return_", c.returns)):
                per_seed = final_per_seed(values)
                for key, q in LINE_STATS.items():
                    v = round(float(np.percentile(per_seed, q)), 4)
                    cell.setdefault(prefix + key, []).append(v)
                rounded = [round(float(v), 4) for v in per_seed]
                cell.setdefault(prefix + "per_seed", []).append(rounded)
    return out


def write_figures(
    curves: list[Curve],
    envs: list[str],
    out: Path,
    summary: dict,
    plan: repro_verdict.Plan | None = None,
) -> list[str]:
    """Draw the six figures into `out`, add their numbers to `summary["redundancy"]` and the
    dissertation's statements to `summary["verdict"]` (`cluster.repro.verdict`, from the
    pairs that finished `plan`; without one, every curve counts as finished); returns the
    file names."""
    envs = ordered([g for g in envs if any(c.env == g for c in curves)])
    summary["redundancy"] = {
        "zerglings": {g: zerglings_of(g) for g in envs},
        "names": {g: env_name(g) for g in envs},  # of the plots: a map file's stem
        "curves": {g: {c.algo: curve_stats(c) for c in curves if c.env == g} for g in envs},
        "final": final_stats(curves, envs),
        "last_evaluations": LAST,
    }
    files = []
    for key, (label, _) in STATS.items():
        files.append(f"{PLOT_PREFIX}_{key}.png")
        _plot_grid(summary["redundancy"]["curves"], envs, key, label, out / files[-1])
    files.append(f"{PLOT_PREFIX}_final.png")
    enemies = {enemy_of(g) for g in envs}
    enemy = enemies.pop() if len(enemies) == 1 else None
    _plot_final(summary["redundancy"]["final"], enemy, out / files[-1])
    plan = plan or repro_verdict.Plan.of_curves(curves)
    summary["verdict"] = repro_verdict.verdict(curves, plan, ENVS)
    files.append(repro_verdict.FIGURE)
    repro_verdict.plot(summary["verdict"], enemy, out / files[-1])
    return files


def _plot_grid(stats: dict, envs: list[str], key: str, label: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(envs), figsize=(4.2 * len(envs), 3.6), squeeze=False)
    colors: dict[str, str] = {}
    for ax, env in zip(axes[0], envs, strict=True):
        for algo, s in stats[env].items():
            kw = {"color": colors[algo]} if algo in colors else {}
            (line,) = ax.plot(s["t_env"], s[key], label=algo, **kw)
            colors[algo] = line.get_color()
            if key == "median":
                ax.fill_between(s["t_env"], s["p25"], s["p75"], alpha=0.2, color=colors[algo])
        seeds = "/".join(str(n) for n in sorted({s["seeds"] for s in stats[env].values()}))
        lings = zerglings_of(env)
        count = "units drawn per episode" if lings is None else f"{lings} zerglings"
        ax.set_title(f"{env_name(env)} ({count}, {seeds} seeds)")
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
        if key != "variance":
            ax.set_ylim(-0.02, 1.02)
    axes[0][0].set_ylabel(label)
    axes[0][0].legend(loc="upper left", fontsize=8)
    fig.suptitle(f"{label}, most redundant zerglings (left) to fewest (right)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_final(final: dict, enemy: str | None, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    for ax, prefix, label in ((axes[0], "", "win rate"), (axes[1], "return_", "return")):
        for algo, s in final.items():
            gen = np.asarray(s["generated"], dtype=bool)
            files = np.asarray(s.get("map_file", [False] * len(gen)), dtype=bool)
            # a line through the Table 5.1 maps; generated variants (open squares) and map
            # files (open diamonds) beside it (bane_z0 and bane_no_z both have 0 zerglings);
            # the line goes through the first kind present
            groups = [(~gen & ~files, "o", ""), (gen, "s", ", generated bane_z<N>")]
            groups.append((files, "D", ", map files"))
            groups = [g for g in groups if g[0].any()]
            color = None
            for i, (keep, marker, kind) in enumerate(groups):
                x = np.asarray(s["zerglings"], dtype=float)[keep]
                order = np.argsort(x, kind="stable")
                med, lo, hi = (np.asarray(s[prefix + k])[keep][order] for k in LINE_STATS)
                bars = ax.errorbar(
                    x[order],
                    med,
                    yerr=[med - lo, hi - med],
                    capsize=3,
                    color=color,
                    marker="o" if i == 0 else marker,
                    ls="-" if i == 0 else "none",
                    mfc=None if i == 0 else "none",
                    label=algo + ("" if i == 0 else kind),
                )
                color = bars.lines[0].get_color()
        ax.set_xlabel("allied zerglings" + (f" (the enemy: {enemy})" if enemy else ""))
        ax.set_ylabel(f"final {label} (last {LAST} evaluations)")
        ax.grid(alpha=0.3)
        ax.set_title(f"final {label}: median over seeds, bars 25-75%")
    axes[0].set_ylim(-0.02, 1.02)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
