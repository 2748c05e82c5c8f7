"""Learning curves on skirmish (or SMAC) maps, shared by `credit repro emcac` (seed Table 5.2,
Figs. 5.10-5.13) and `credit repro smac` (the value family and RDN).

Each (algorithm, env) pair is one seed-batched LocalTrainer (E = seeds); pairs run in a small
process pool or as Ray tasks on a cluster (`cluster.repro.fanout`). Every evaluation is appended
to `evals/<env>__<algo>.jsonl` as it happens (`<env>__<algo>.g<G>.jsonl` for seed group
G > 0, `cluster.repro.groups`; a long run that dies keeps what it measured, and `load_evals`
rebuilds curves from those files, every seed group of a pair merged into one curve); at
the end summary.json, curves.json and one <prefix>_<map>.png per env are written: test win rate
and test return against env steps, win rate against wall time, and the learner diagnostics
the experiment names.

Summary per (env, algo), win rates in [0, 1]:
    median_win_rate_last10 / mean_win_rate_last10: each seed's mean test win rate over its last
        10 evaluations, then the median / mean over seeds (Table 5.2's two numbers);
    steps_to_50 / steps_to_80 / steps_to_95: the first evaluation's t_env at which the
        median-over-seeds curve reaches 0.5 / 0.8 / 0.95, or None if it never does;
    steps_to_*_smoothed: the same on the trailing mean of the median curve over SMOOTH
        evaluations, at the t_env of the window's last evaluation. One evaluation is 20 greedy
        episodes per seed, and a barely trained greedy policy can win one of them by luck
        (skirmish/2s3z at 10k steps, results/pg/README.md); over a window a single lucky or
        unlucky evaluation cannot decide the figure.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from cluster.repro import groups as repro_groups
from cluster.repro.fanout import run_pairs
from cluster.repro.pairs import FanOutConfig, Pair, StatusLine
from cluster.repro.resume import PairJournal, PairStore, ResumeConfig

log = logging.getLogger(__name__)

LAST = 10  # evaluations averaged for the final win rate (Table 5.2)
SMOOTH = 5  # evaluations in the trailing window of the smoothed steps-to figures
LEVELS = (50, 80, 95)  # win rates (%) of the steps-to figures
LEARNER_KEYS = (
    "kl_masked_fraction",
    "kl_mean",
    "entropy",
    "loss_critic",
    "loss_critic_extra",
    "advantage_abs_mean",
    "loss_td",
    "q_taken_mean",
    "grad_norm",
    "loss_agent",
    "q_tot_mean",
    "lrp_conservation_gap",
)


@dataclass(frozen=True)
class Curve:
    """Every evaluation of one (algo, env) pair: t_env [K]; won and returns [K][seeds];
    learner diagnostics at each evaluation (means over seeds and over the updates since the
    previous evaluation; only keys the learner has); wall [K] seconds since the pair started;
    commits: the code's commits it was trained at (two or more if it was resumed at another);
    groups: the seed groups it holds, [{group, seeds, evaluations}] (`cluster.repro.groups`;
    empty in records made before groups existed: group 0)."""

    algo: str
    env: str
    t_env: list[int]
    won: list[list[float]]
    returns: list[list[float]]
    wall_s: float
    learner: list[dict[str, float]] = field(default_factory=list)
    wall: list[float] = field(default_factory=list)
    commits: list[str] = field(default_factory=list)
    groups: list[dict] = field(default_factory=list)


@dataclass(frozen=True)
class PairOutput:
    """What a pair's process hands back: its curve and, when asked for, its final checkpoint
    as files (path relative to the checkpoint folder -> bytes), written by the driver so that
    a pair on another node saves into the driver's output folder."""

    curve: Curve
    checkpoint: tuple[tuple[str, bytes], ...] = ()


def run_pair(
    algo: str,
    env: str,
    seeds: int,
    overrides: list[str],
    checkpoint: bool = False,
    resume: ResumeConfig | None = None,
    group: int = 0,
    report: Callable[[str], None] | None = None,
) -> PairOutput:
    """Train `seeds` seeds of `algo` on `env` in one seed-batched trainer.

    Args:
        checkpoint: also return the final checkpoint (every seed, `credit train`'s format:
            networks, optimisers and counters, without the replay, which on the larger maps
            is gigabytes).
        resume: where the pair checkpoints every `resume.every` env steps and continues
            from (`cluster.repro.resume`); None: no checkpoints.
        group: the pair's seed group (`cluster.repro.groups`; its run.seed is among
            `overrides`).
        report: called with one JSON line per evaluation (the pair's evaluation log).
    """
    from cluster.config.train import load_train_config
    from cluster.launch.local import LocalTrainer
    from cluster.process import configure

    with PairJournal(resume, Pair(algo, env, group), report) as journal:
        cfg = load_train_config(algo, env, [], overrides + journal.overrides())
        configure(cfg.run)  # the pair's torch threads (run.torch_threads) and seed
        trainer = LocalTrainer(cfg, n_ensemble=seeds)
        journal.attach(trainer)

        def on_eval(records) -> None:
            means = trainer.core.take_metric_means()  # over the updates since the last evaluation
            row = {
                "env": env,
                "algo": algo,
                "t_env": records[0].t_env,
                "won": [float(r.test_won_mean or 0.0) for r in records],
                "returns": [r.test_return_mean for r in records],
            }
            journal.add({**row, **{k: v for k, v in means.items() if k in LEARNER_KEYS}})

        trainer.train(on_eval=on_eval)
        if not journal.rows or journal.rows[-1]["t_env"] != trainer.core.t_env:
            on_eval(trainer.core.evaluate())
        journal.finish()
    files: tuple[tuple[str, bytes], ...] = ()
    if checkpoint:
        with tempfile.TemporaryDirectory() as tmp:
            trainer.save(Path(tmp) / "ckpt", replay=False)
            root = Path(tmp) / "ckpt"
            files = tuple(
                (str(f.relative_to(root)), f.read_bytes())
                for f in sorted(root.rglob("*"))
                if f.is_file()
            )
    curve = curve_of(algo, env, journal.rows)
    groups = [{"group": group, "seeds": seeds, "evaluations": len(journal.rows)}]
    curve = replace(curve, wall_s=journal.wall_s, commits=journal.commits, groups=groups)
    return PairOutput(curve, files)


def write_checkpoint(folder: Path, files: tuple[tuple[str, bytes], ...]) -> None:
    """Write a pair's checkpoint files (PairOutput.checkpoint) into `folder`, replacing what
    was there only once every file is written."""
    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    for rel, data in files:
        path = tmp / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    shutil.rmtree(folder, ignore_errors=True)
    os.replace(tmp, folder)


def load_evals(
    log_dir: Path, algos: list[str], envs: list[str], until: int | None = None
) -> list[Curve]:
    """Curves rebuilt from the per-pair evaluation logs (pairs without a log are skipped),
    each pair's seed groups merged into one curve (`cluster.repro.groups.merge`). With
    `until`, each curve ends at its first evaluation at or past `until` env steps, so that
    runs of different lengths are summarised at one budget."""
    curves = [load_pair(log_dir, algo, env, until) for env in envs for algo in algos]
    return [c for c in curves if c is not None]


def load_pair(
    log_dir: Path,
    algo: str,
    env: str,
    until: int | None = None,
    finished_at: int | None = None,
) -> Curve | None:
    """One pair's curve from the logs of all its seed groups (None without a log; with
    `finished_at`, only the groups whose log reaches it: `cluster.repro.groups.load`)."""
    pair = Pair(algo, env)
    loaded = repro_groups.load(log_dir, pair.key, pair.label, until, finished_at)
    if loaded is None:
        return None
    rows, info = loaded
    return replace(curve_of(algo, env, rows), commits=info["commits"], groups=info["groups"])


def with_other_groups(
    curves: list[Curve], log_dir: Path, t_max: dict[tuple[str, str], int]
) -> list[Curve]:
    """The curves a run trained, each replaced by the merge of all its pair's finished seed
    groups (from their logs in `log_dir`: those that reach the pair's t_max, `t_max[(env,
    algo)]`) where other groups have logs there; a group still training is left out."""
    return repro_groups.with_finished_groups(curves, log_dir, t_max, lambda c: c.env, load_pair)


def curve_of(algo: str, env: str, rows: list[dict]) -> Curve:
    """A pair's curve from its evaluation log's rows (its wall time: the last row's)."""
    commits = list(dict.fromkeys(r["commit"] for r in rows if "commit" in r))
    return Curve(
        algo,
        env,
        [r["t_env"] for r in rows],
        [r["won"] for r in rows],
        [r["returns"] for r in rows],
        float(rows[-1]["wall_s"]),
        [{k: r[k] for k in LEARNER_KEYS if k in r} for r in rows],
        [float(r["wall_s"]) for r in rows],
        commits,
    )


def steps_to(t_env: np.ndarray, median_curve: np.ndarray, level: float) -> int | None:
    """First t_env at which the median curve reaches `level`, or None."""
    hit = np.flatnonzero(median_curve >= level - 1e-9)
    return int(t_env[hit[0]]) if hit.size else None


def trailing_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of each run of `window` consecutive values: [K] -> [K - window + 1] (empty when
    K < window); entry i covers values i .. i + window - 1."""
    if values.size < window:
        return np.empty(0)
    return np.convolve(values, np.ones(window) / window, mode="valid")


def final_per_seed(values: list[list[float]]) -> np.ndarray:
    """Each seed's final value: its mean over the last LAST evaluations ([K][seeds] -> [seeds])."""
    return np.asarray(values, dtype=float)[-LAST:].mean(axis=0)


def summarise_curve(t_env: list[int], won: list[list[float]]) -> dict:
    """Table 5.2's numbers and the steps to 50% / 80% / 95% for one pair (module docstring).

    Args:
        t_env: [K] evaluation times.
        won: [K][seeds] test win rates.
    """
    w = np.asarray(won, dtype=float)
    per_seed = final_per_seed(w)
    median_curve = np.median(w, axis=1)
    t = np.asarray(t_env)
    smooth = trailing_mean(median_curve, SMOOTH)
    t_smooth = t[SMOOTH - 1 :]
    return {
        "median_win_rate_last10": float(np.median(per_seed)),
        "mean_win_rate_last10": float(np.mean(per_seed)),
        **{f"steps_to_{p}": steps_to(t, median_curve, p / 100) for p in LEVELS},
        **{f"steps_to_{p}_smoothed": steps_to(t_smooth, smooth, p / 100) for p in LEVELS},
        "seeds": int(w.shape[1]),
    }


def summarise(curves: list[Curve]) -> dict:
    """{env: {algo: summarise_curve(...) + final return median, wall time, evaluations,
    commits and the seed groups merged into the curve, [{group, seeds, evaluations}]}}."""
    out: dict = {}
    for c in curves:
        cell = summarise_curve(c.t_env, c.won)
        cell["median_return_last10"] = float(np.median(np.asarray(c.returns)[-LAST:].mean(0)))
        cell["t_env"] = int(c.t_env[-1])
        cell["evaluations"] = len(c.t_env)
        cell["wall_s"] = round(c.wall_s, 1)
        cell["commits"] = c.commits
        cell["groups"] = c.groups or [
            {"group": 0, "seeds": len(c.won[0]), "evaluations": len(c.t_env)}
        ]
        out.setdefault(c.env, {})[c.algo] = cell
    return out


def headings(mine: list[Curve], env: str) -> tuple[str, dict[str, str]]:
    """The curves figure's heading and each algo's legend label for one env's curves: "<env>:
    median of N seeds" and the algo names when every algo has N seeds; otherwise each label
    carries its algo's own count (a pair still running has fewer seeds than the others)."""
    counts = {c.algo: len(c.won[0]) if c.won else 0 for c in mine}
    if len(set(counts.values())) < 2:
        n = next(iter(counts.values()), 0)
        return f"{env}: median of {n} seeds, 25-75 percentile band", {a: a for a in counts}
    labels = {a: f"{a} ({n} seed{'s' if n != 1 else ''})" for a, n in counts.items()}
    return f"{env}: median of each algo's seeds (in the legend), 25-75 percentile band", labels


def logged(
    mine: list[Curve], diagnostics: tuple[tuple[str, str], ...]
) -> tuple[tuple[str, str], ...]:
    """The (key, label) diagnostics that at least one of `mine` logged (RDN's critic panels
    stay out of a figure without RDN)."""
    return tuple((k, lab) for k, lab in diagnostics if any(k in d for c in mine for d in c.learner))


def plot(
    curves: list[Curve],
    env: str,
    path: Path,
    diagnostics: tuple[tuple[str, str], ...] = (),
    title: str | None = None,
) -> None:
    """Median test win rate and test return against env steps, and win rate against wall
    time, with the 25-75 percentile band, one line per algo; then one panel per learner
    diagnostic (key, label) that some algo logged, at each evaluation (means over seeds).
    `title` replaces the default heading, "<env>: median of N seeds" when every algo has N
    seeds; when they differ, each algo's legend entry carries its own count and the heading
    says so."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mine = [c for c in curves if c.env == env]
    diagnostics = logged(mine, diagnostics)
    panels = 3 + len(diagnostics)
    cols = 3 if panels > 4 else 2
    rows = -(-panels // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 4 * rows), squeeze=False)
    flat = list(axes.flat)
    heading, labels = headings(mine, env)
    names = ["test win rate", "test return", "test win rate", *(lab for _, lab in diagnostics)]
    for c in mine:
        t = np.asarray(c.t_env)
        wall = np.asarray(c.wall) if len(c.wall) == len(c.t_env) else None
        color = None
        for ax, data, x in (
            (flat[0], c.won, t),
            (flat[1], c.returns, t),
            (flat[2], c.won, wall),
        ):
            if x is None:
                continue
            r = np.asarray(data)
            (line,) = ax.plot(x, np.median(r, axis=1), label=labels[c.algo], color=color)
            color = line.get_color()
            ax.fill_between(
                x,
                np.percentile(r, 25, axis=1),
                np.percentile(r, 75, axis=1),
                alpha=0.2,
                color=color,
            )
        for ax, (key, _) in zip(flat[3:], diagnostics, strict=False):
            points = [(x, d[key]) for x, d in zip(c.t_env, c.learner, strict=False) if key in d]
            if points:
                ax.plot(*zip(*points, strict=True), label=c.algo, color=color)
    for i, ax in enumerate(flat):
        if i >= len(names):
            ax.set_visible(False)
            continue
        ax.set_xlabel("wall seconds" if i == 2 else "env steps")
        ax.set_ylabel(names[i])
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(loc="upper left")
    flat[0].set_ylim(-0.02, 1.02)
    flat[2].set_ylim(-0.02, 1.02)
    fig.suptitle(title or heading)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(
    algos: list[str],
    envs: list[str],
    seeds: int,
    overrides: list[str],
    fan: FanOutConfig,
    log_dir: Path | None = None,
    checkpoint_dir: Path | None = None,
    total_steps: int = 0,
    resume: ResumeConfig | None = None,
    group: int = 0,
) -> list[Curve]:
    """Every (algo, env) pair where `fan` says, as seed group `group` (its run.seed among
    `overrides`; `cluster.repro.groups`); curves in (env, algo) order. Each pair's
    evaluations go to log_dir/<env>__<algo>.jsonl as they happen and, with `checkpoint_dir`,
    its final checkpoint to checkpoint_dir/<env>__<algo>/ as it finishes. With
    `total_steps` (every pair's t_max together), a status line shows the env steps done and
    each pair's latest median win rate. With `resume` (and its output folder), pairs
    checkpoint, continue from their checkpoints and are skipped when already finished
    (`cluster.repro.resume`)."""
    pairs = [Pair(a, g, group) for g in envs for a in algos]

    def on_result(pair: Pair, out: PairOutput) -> None:
        if checkpoint_dir is not None:
            write_checkpoint(checkpoint_dir / pair.key, out.checkpoint)

    args = (seeds, overrides, checkpoint_dir is not None, resume, group)
    status = StatusLine(total_steps, "won", "win") if total_steps else None
    store = None
    if resume is not None and resume.out is not None:
        store = PairStore(resume, _encode, _decode)
    outputs = run_pairs(run_pair, pairs, args, fan, log_dir, on_result, status, store)
    return [o.curve for o in outputs]


def _encode(out: PairOutput) -> dict:
    return dict(out.curve.__dict__)  # the final checkpoint's files are in OUT/checkpoints


def _decode(d: dict) -> PairOutput:
    return PairOutput(Curve(**d))
