"""What `credit demo` shows at the end of its training: the trained policy's greedy win rate,
a learning-curve PNG and a GIF of the policy winning, all from the run's folder.

    report = write_report(Path("runs/demo"), episodes=100)
    print(report.win_rate, report.curve_png, report.gif)

Everything is read back from what the run wrote (config.yaml, metrics.jsonl, checkpoint/),
so the figures describe the saved policy, not a process's memory of it.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

from actors.envs.registry import make_vec_env
from cluster.config.schema import read_yaml
from cluster.config.train import build_train_config
from cluster.core import TrainerCore
from cluster.process import configure
from cluster.repro.curves import Curve, plot

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DemoReport:
    """The end of a demo run.

    Attributes:
        win_rate: greedy win rate of the saved policy over `episodes` fresh episodes.
        episodes: how many greedy episodes that rate is over.
        return_mean: their mean return.
        t_env: env steps the policy was trained for.
        curve_png: the learning curve (greedy win rate and return against env steps).
        gif: a replay of one greedy episode; `gif_won` says whether it is a win.
        gif_won: whether the replayed episode was won.
    """

    win_rate: float
    episodes: int
    return_mean: float
    t_env: int
    curve_png: Path
    gif: Path
    gif_won: bool


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
    """Evaluate the checkpoint in `run_dir` greedily, plot its curve and replay a win.

    Args:
        run_dir: a finished `credit train` folder on a skirmish map.
        episodes: greedy episodes for the final win rate (fresh seeds, not the training's).
        gif_tries: greedy episodes played at most until one is won for the GIF.

    Returns:
        The figures and the paths written (run_dir/learning_curve.png, run_dir/policy.gif).
    """
    from actors.episode_gifs import render_policy_episode

    cfg = build_train_config(read_yaml(run_dir / "config.yaml"))
    configure(cfg.run)  # the run's torch threads, as it trained
    core = TrainerCore(cfg, 1)
    core.restore(run_dir / "checkpoint")
    learning = core.learning
    seed = cfg.run.seed + 50_000  # episodes neither training nor its evaluations played
    evaluator = learning.local_worker(make_vec_env(cfg.env.id, episodes, seed=seed), seed)
    learning.sync_worker(evaluator)
    result = evaluator.run_round(greedy=True)

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
        win_rate=float(result.won.mean()),
        episodes=episodes,
        return_mean=float(result.returns.mean()),
        t_env=core.t_env,
        curve_png=curve_png,
        gif=Path(replay["out"]),
        gif_won=replay["battle_won"],
    )
