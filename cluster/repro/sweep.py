"""Hyper-parameter sweeps on Ray Tune: every (configuration, seed) a Tune trial that is one
`credit train` run, then the configurations ranked by a statistic over their seeds.

The search space is made explicit before Tune starts: the grid's cross product (`--grid`),
times `samples` draws from Tune's own samplers (`tune.choice` / `uniform` / `loguniform`,
with a recorded seed) for the random keys. Every configuration is run with the same seeds
(`run.seed` 0..seeds-1), so Tune runs a grid over (configuration, seed) and the sweep's
statistics compare configurations on equal seeds.

A trial writes `credit train`'s outputs (config.yaml, metrics.jsonl, summary.json,
checkpoint/, and what run.loggers adds) to OUT/trials/<name>/. A trial whose process or
node dies is restarted by Tune (`max_failures`); it continues from its checkpoint when it
has one (run.save_interval), else starts over. Tune keeps its own state in OUT/tune/: the
same `credit sweep` command run again resumes an interrupted sweep (finished trials are kept,
the others rerun). On a multi-node cluster OUT must be a folder every node sees (Tune's
storage_path).
"""

from __future__ import annotations

import json
import logging
import os
import socket
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cluster.repro import aggregate

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Sweep:
    """What to train: algorithm, env, config files and fixed --set overrides of every trial;
    the configurations (each a {key: value} of overrides) and the seeds of each."""

    algo: str | None
    env: str | None
    files: tuple[str, ...]
    sets: tuple[str, ...]
    points: tuple[dict, ...]
    seeds: int

    def trials(self) -> list[dict]:
        return [
            {"name": f"p{i:03d}_s{s}", "point": i, "seed": s}
            for i in range(len(self.points))
            for s in range(self.seeds)
        ]

    def argv(self, trial: dict, out: Path) -> list[str]:
        """The `credit train` command line of one trial."""
        argv = ["train", "--out", str(out), "--seed", str(trial["seed"])]
        argv += ["--algo", self.algo] if self.algo else []
        argv += ["--env", self.env] if self.env else []
        for f in self.files:
            argv += ["--config", f]
        for s in self.argv_sets(self.points[trial["point"]]):
            argv += ["--set", s]
        return argv

    def argv_sets(self, point: dict) -> list[str]:
        """The --set overrides of a configuration: the fixed ones, then its own."""
        return [*self.sets, *(f"{k}={json.dumps(v)}" for k, v in point.items())]


def points(grid: dict[str, list], random: dict[str, object], samples: int, seed: int) -> list:
    """The configurations: the grid's cross product, each with `samples` draws of the random
    keys (Tune Domain objects, sampled with numpy generator `seed`)."""
    combos: list[dict] = [{}]
    for key, values in grid.items():
        combos = [{**c, key: v} for c in combos for v in values]
    if not random:
        return combos
    rng = np.random.default_rng(seed)
    out = []
    for c in combos:
        for _ in range(samples):
            drawn = {k: d.sample(random_state=rng) for k, d in random.items()}
            out.append(
                {**c, **{k: v.item() if hasattr(v, "item") else v for k, v in drawn.items()}}
            )
    return out


def run_trial(config: dict, sweep: Sweep, root: str) -> None:
    """Tune's function trainable: one `credit train` run in root/trials/<name>/; resumes
    from the trial's checkpoint when a previous attempt left one."""
    from ray import tune

    from cluster.cli import main

    trial = config["trial"]
    out = Path(root) / "trials" / trial["name"]
    where = f"{socket.gethostname()} (pid {os.getpid()})"
    if (out / "summary.json").exists():  # finished before the sweep was interrupted
        print(f"trial {trial['name']} already finished: kept", file=sys.stderr, flush=True)
    else:
        print(f"trial {trial['name']} started on {where}", file=sys.stderr, flush=True)
        argv = sweep.argv(trial, out)
        if (out / "checkpoint" / "learner.pt").exists():
            argv = ["train", "--resume", str(out)]
        code = main(argv)
        if code != 0:
            raise RuntimeError(f"trial {trial['name']}: `credit {' '.join(argv)}` exited {code}")
    summary = json.loads((out / "summary.json").read_text())
    tune.report({k: v for k, v in summary.items() if isinstance(v, int | float)})


def run(sweep: Sweep, out: Path, cpus_per_trial: float, max_failures: int) -> None:
    """Every trial on Ray Tune (this driver already connected to Ray); resumes the Tune
    experiment in out/tune when there is one."""
    from ray import tune

    root = str(out.resolve())
    trainable = tune.with_resources(
        tune.with_parameters(run_trial, sweep=sweep, root=root), {"cpu": cpus_per_trial}
    )
    path = Path(root) / "tune"
    if tune.Tuner.can_restore(str(path)):
        log.warning("resuming the sweep in %s (finished trials are kept)", path)
        tuner = tune.Tuner.restore(str(path), trainable, resume_errored=True)
    else:
        run_config = tune.RunConfig(
            name="tune",
            storage_path=root,
            failure_config=tune.FailureConfig(max_failures=max_failures),
            verbose=0,
        )
        tuner = tune.Tuner(
            trainable,
            param_space={"trial": tune.grid_search(sweep.trials())},
            tune_config=tune.TuneConfig(
                trial_dirname_creator=lambda t: t.config["trial"]["name"],
                reuse_actors=False,
            ),
            run_config=run_config,
        )
    grid = tuner.fit()
    failed = [r for r in grid if r.error is not None]
    if failed:
        log.warning("%d trials failed after their retries: %s", len(failed), failed[0].error)


def trial_statistic(folder: Path, metric: str, last: int) -> float | None:
    """Mean of `metric` over a finished trial's last `last` evaluations (None if the trial
    has not finished: no summary.json)."""
    if not (folder / "summary.json").exists():
        return None
    rows = [json.loads(x) for x in (folder / "metrics.jsonl").read_text().splitlines() if x]
    values = [r[metric] for r in rows if r.get(metric) is not None][-last:]
    if not values:
        raise ValueError(f"{folder / 'metrics.jsonl'} has no {metric!r}")
    return float(np.mean(values))


def rank(sweep: Sweep, out: Path, metric: str, last: int, reps: int, seed: int) -> list[dict]:
    """The configurations best first by the IQM over seeds of each trial's statistic, with
    its stratified bootstrap interval (`cluster.repro.aggregate`); unfinished trials left
    out and counted."""
    from rliable import metrics

    table = []
    for i, point in enumerate(sweep.points):
        names = [f"p{i:03d}_s{s}" for s in range(sweep.seeds)]
        got = [trial_statistic(out / "trials" / n, metric, last) for n in names]
        done = [v for v in got if v is not None]
        row = {"point": i, "config": point, "runs": len(done), "missing": len(got) - len(done)}
        if done:
            iqm, ci = aggregate.interval(
                np.asarray(done)[:, None], metrics.aggregate_iqm, reps, seed
            )
            row |= {"iqm": iqm, "ci": ci, "mean": float(np.mean(done)), "values": done}
        table.append(row)
    table.sort(key=lambda r: -r.get("iqm", -np.inf))
    for i, row in enumerate(table):
        row["rank"] = i + 1
    return table
