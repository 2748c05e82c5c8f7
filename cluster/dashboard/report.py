"""What `credit demo` shows at the end of its training: the saved policies' greedy win rates
on fresh episodes (the final one, and the one kept at the best evaluation with
run.keep_best), a learning-curve PNG and a GIF of the shown policy winning, all from the
run's folder.

    report = write_report(Path("runs/demo"), episodes=100)
    print(report.shown.win_rate, report.final.win_rate, report.curve_png, report.gif)

Everything is read back from what the run wrote (config.yaml, metrics.jsonl, checkpoint/,
best/), so the figures describe the saved policies, not a process's memory of them.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, replace
from pathlib import Path

from actors.envs.registry import make_vec_env
from cluster.config.schema import read_yaml
from cluster.config.train import TrainConfig, build_train_config
from cluster.core import BEST_FILE, BEST_FOLDER, TrainerCore
from cluster.learning import Learning
from cluster.process import configure
from cluster.repro.curves import Curve, plot

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PolicyResult:
    """One saved policy's greedy result on fresh episodes.

    Attributes:
        folder: the checkpoint folder it was read from.
        t_env: env steps the policy was trained for.
        win_rate: its greedy win rate over the report's fresh episodes.
        return_mean: their mean return.
    """

    folder: Path
    t_env: int
    win_rate: float
    return_mean: float


@dataclass(frozen=True)
class DemoReport:
    """The end of a demo run.

    Attributes:
        final: the policy training ended with (checkpoint/).
        best: the policy kept at the training's best greedy evaluation (best/, written with
            run.keep_best), or None when the run kept none.
        best_evaluation: that evaluation as the run logged it (best/best.json), or None.
        evaluation_episodes: greedy episodes per evaluation during training (run.test_episodes).
        episodes: how many fresh greedy episodes each win rate is over.
        curve_png: the learning curve (greedy win rate and return against env steps).
        gif: a replay of one greedy episode of the shown policy; `gif_won` says whether it
            is a win.
        gif_won: whether the replayed episode was won.
    """

    final: PolicyResult
    best: PolicyResult | None
    best_evaluation: dict | None
    evaluation_episodes: int
    episodes: int
    curve_png: Path
    gif: Path
    gif_won: bool

    @property
    def shown(self) -> PolicyResult:
        """The policy the demo presents (its GIF): the kept best one, else the final one."""
        return self.best or self.final


def load_curve(run_dir: Path, algo: str, env: str) -> Curve:
    """The run's evaluations (metrics.jsonl) as a one-seed Curve."""
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    if not rows:
        raise ValueError(f"{run_dir / 'metrics.jsonl'} holds no evaluation")
    return Curve(
        algo=algo,
        env=env,
        t_env=[r["t_env"] for r in rows],
        won=[[r.get("test_won_mean", 0.0)] for r in rows],
        returns=[[r["test_return_mean"]] for r in rows],
        wall_s=rows[-1]["wall_s"],
        wall=[r["wall_s"] for r in rows],
    )


def write_report(run_dir: Path, episodes: int = 100, gif_tries: int = 10) -> DemoReport:
    """Evaluate the run's saved policies greedily, plot its curve and replay a win.

    Both the final policy (checkpoint/) and, where the run kept one (run.keep_best), the
    policy of its best evaluation (best/) play the same fresh episodes; the GIF shows the
    best one when there is one.

    Args:
        run_dir: a finished `credit train` folder on a skirmish map.
        episodes: greedy episodes for each win rate (fresh seeds, not the training's).
        gif_tries: greedy episodes played at most until one is won for the GIF.

    Returns:
        The figures and the paths written (run_dir/learning_curve.png, run_dir/policy.gif).
    """
    from actors.episode_gifs import render_policy_episode

    cfg = build_train_config(read_yaml(run_dir / "config.yaml"))
    cfg = replace(cfg, run=replace(cfg.run, keep_best=False))  # only reads checkpoints
    configure(cfg.run)  # the run's torch threads, as it trained
    seed = cfg.run.seed + 50_000  # episodes neither training nor its evaluations played
    final, learning = _evaluate(cfg, run_dir / "checkpoint", episodes, seed)
    best, best_evaluation = None, None
    if (run_dir / BEST_FOLDER / BEST_FILE).exists():
        best, learning = _evaluate(cfg, run_dir / BEST_FOLDER, episodes, seed)
        best_evaluation = json.loads((run_dir / BEST_FOLDER / BEST_FILE).read_text())

    curve_png = run_dir / "learning_curve.png"
    curve = load_curve(run_dir, cfg.algo_name, cfg.env.id)
    title = f"{cfg.algo_name} on {cfg.env.id}: greedy evaluations during `credit demo`"
    plot([curve], cfg.env.id, curve_png, title=title)

    player = learning.local_worker(make_vec_env(cfg.env.id, 1, seed=seed + 1), seed + 1)
    learning.sync_worker(player)
    replay = render_policy_episode(
        player, run_dir / "policy.gif", f"{cfg.algo_name} {cfg.env.id}", tries=gif_tries
    )
    return DemoReport(
        final=final,
        best=best,
        best_evaluation=best_evaluation,
        evaluation_episodes=cfg.run.test_episodes,
        episodes=episodes,
        curve_png=curve_png,
        gif=Path(replay["out"]),
        gif_won=replay["battle_won"],
    )


def _evaluate(
    cfg: TrainConfig, folder: Path, episodes: int, seed: int
) -> tuple[PolicyResult, Learning]:
    """Restore the checkpoint in `folder` and play `episodes` greedy episodes from `seed`;
    returns the result and the restored learner."""
    core = TrainerCore(cfg, 1)
    core.restore(folder)
    learning = core.learning
    evaluator = learning.local_worker(make_vec_env(cfg.env.id, episodes, seed=seed), seed)
    learning.sync_worker(evaluator)
    result = evaluator.run_round(greedy=True)
    won, returns = float(result.won.mean()), float(result.returns.mean())
    return PolicyResult(folder, core.t_env, win_rate=won, return_mean=returns), learning
