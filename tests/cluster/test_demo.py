"""`credit demo`: the report it ends with (win rate, learning curve, a replay GIF), and the
whole command on the local multi-process cluster."""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from PIL import Image

from cluster.cli import main
from cluster.commands import demo
from cluster.dashboard.report import DemoReport, PolicyResult, write_report
from cluster.progress import Progress

ROOT = Path(__file__).resolve().parents[2]


def test_the_report_evaluates_the_saved_policies_and_writes_curve_and_gif(tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["train", "--algo", "qmix", "--env", "skirmish/3m", "--t-max", "200", "--out", str(out)]
    argv += ["--set", "run.num_envs=2", "--set", "run.test_interval=60"]
    argv += ["--set", "run.test_episodes=2", "--set", "replay.batch_size=4"]
    argv += ["--set", "run.keep_best=true"]
    assert main(argv) == 0
    report = write_report(out, episodes=4, gif_tries=1)
    assert report.episodes == 4 and report.evaluation_episodes == 2
    assert report.final.t_env == json.loads((out / "summary.json").read_text())["t_env"]
    assert report.final.folder == out / "checkpoint" and 0.0 <= report.final.win_rate <= 1.0
    kept = json.loads((out / "best" / "best.json").read_text())
    assert report.best is not None and report.best_evaluation == kept
    assert report.shown is report.best and report.best.t_env == kept["t_env"] <= report.final.t_env
    assert report.curve_png == out / "learning_curve.png"
    with Image.open(report.curve_png) as png:
        assert png.format == "PNG" and png.size[0] > 500
    with Image.open(report.gif) as gif:
        assert gif.format == "GIF" and gif.n_frames >= 5  # t = 0, steps, the closing frames


def test_without_a_kept_policy_the_report_shows_the_final_one(tmp_path):
    out = tmp_path / "run"
    argv = ["train", "--algo", "qmix", "--env", "skirmish/3m", "--t-max", "100", "--out", str(out)]
    argv += ["--set", "run.num_envs=2", "--set", "run.test_episodes=2"]
    argv += ["--set", "replay.batch_size=4"]
    assert main(argv) == 0
    report = write_report(out, episodes=2, gif_tries=1)
    assert report.best is None and report.best_evaluation is None
    assert report.shown is report.final


def _report(tmp_path: Path, best_t: int | None, best_won: float = 0.9) -> DemoReport:
    (tmp_path / "summary.json").write_text(json.dumps({"wall_s": 80.0}))
    (tmp_path / "metrics.jsonl").write_text(json.dumps({"wall_s": 12.0}) + "\n")
    final = PolicyResult(tmp_path / "checkpoint", 60_100, win_rate=0.78, return_mean=17.4)
    best = None if best_t is None else PolicyResult(tmp_path / "best", best_t, 0.97, 19.6)
    kept = None if best_t is None else {"t_env": best_t, "test_won_mean": best_won}
    return DemoReport(final, best, kept, 20, 100, tmp_path / "c.png", tmp_path / "p.gif", True)


@pytest.mark.parametrize(
    "best_t, expected",
    [
        (
            58_000,
            "a greedy win rate of 0.97 (97 of 100 fresh episodes, mean return 19.6) with the "
            "policy kept at its best greedy evaluation during training (58,000 env steps: win "
            "rate 0.90 over 20 episodes); the final policy, after 60,100 env steps, won 78 of "
            "100. Training took 80 s",
        ),
        (
            60_100,
            "a greedy win rate of 0.97 (97 of 100 fresh episodes, mean return 19.6) after "
            "60,100 env steps; its evaluation at the end of training (0.90 over 20 episodes) "
            "was its best, so the kept policy is the final one. Training",
        ),
        (
            None,
            "a greedy win rate of 0.78 (78 of 100 fresh episodes, mean return 17.4) after "
            "60,100 env steps. Training took 80 s with 2 Ray rollout actors (12 s",
        ),
    ],
)
def test_the_closing_lines_name_the_kept_and_the_final_policy(tmp_path, capsys, best_t, expected):
    args = argparse.Namespace(algo="qmix", env="skirmish/3m", actors=2)
    demo._print_report(args, tmp_path, _report(tmp_path, best_t))
    printed = capsys.readouterr().out
    assert expected in printed.replace("\n", " ")
    assert ("best/ (the kept one)" in printed) == (best_t is not None)


def test_progress_lines_give_env_steps_win_rate_and_throughput(caplog):
    bar = Progress(total=1000, every_s=0.0)  # not a terminal under pytest: log lines
    with caplog.at_level(logging.INFO, logger="cluster.progress"):
        bar.update(100, "win rate 0.10")
        time.sleep(0.05)
        bar.update(300, "win rate 0.40")
        time.sleep(0.05)
        bar.update(300, "win rate 0.40")  # no new steps yet: the last rate stays, not 0
    first, second, third = (r.getMessage() for r in caplog.records)
    assert first == "t_env 100/1000 win rate 0.10"
    line = re.fullmatch(r"t_env 300/1000 win rate 0\.40 \| ([\d,]+) env steps/s", second)
    assert line and int(line.group(1).replace(",", "")) > 0
    assert third == second


def test_the_demo_needs_a_skirmish_map(capsys):
    assert main(["demo", "--env", "matrix/two_step", "--no-wait"]) == 2
    assert "--env must be a skirmish map" in capsys.readouterr().err


def run_demo(tmp_path: Path, *extra: str) -> tuple[subprocess.CompletedProcess, Path]:
    out = tmp_path / "demo"
    env = {**os.environ, "CREDIT_STATE_DIR": str(tmp_path / "state"), "PYTHONUNBUFFERED": "1"}
    done = subprocess.run(
        [sys.executable, "-m", "cluster.cli", "demo", "--out", str(out), *extra],
        cwd=ROOT,
        env=env,
        stdin=subprocess.DEVNULL,  # not a terminal: the demo must not wait for Ctrl-C
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done, out


def printed_win_rate(stdout: str) -> float:
    found = re.search(r"reached a greedy win rate of (\d\.\d\d) \(", stdout)
    assert found, stdout
    return float(found.group(1))


@pytest.mark.slow
def test_a_short_demo_runs_the_cluster_and_ends_without_waiting(tmp_path):
    done, out = run_demo(
        tmp_path, "--t-max", "600", "--test-interval", "300", "--episodes", "4", "--actors", "1"
    )
    assert done.stdout.startswith("live dashboard: http://127.0.0.1:")
    assert "stdin is not a terminal, so the dashboard closes now" in done.stdout
    assert 0.0 <= printed_win_rate(done.stdout) <= 1.0
    for name in ("learning_curve.png", "policy.gif", "summary.json", "cluster.json"):
        assert (out / name).is_file(), name
    assert f"learning curve:             {out / 'learning_curve.png'}" in done.stdout
    assert json.loads((out / "summary.json").read_text())["mode"] == "cluster"
    assert "win rate" in done.stderr  # the progress lines


@pytest.mark.slow
def test_the_default_demo_learns_3m(tmp_path):
    """The judged claim: the default `credit demo` ends with a greedy win rate of at least
    0.8 and a GIF of a won episode (about 3 minutes of training on 2 cores)."""
    done, out = run_demo(tmp_path, "--no-wait")
    assert printed_win_rate(done.stdout) >= 0.8
    kept = ("with the policy kept at its best greedy evaluation", "the kept policy is the final")
    assert any(words in done.stdout for words in kept), done.stdout
    assert f"the trained policy winning: {out / 'policy.gif'}" in done.stdout
