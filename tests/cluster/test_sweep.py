"""`credit sweep` on Ray Tune: the search space made explicit, bad input, and (slow) a
2 values x 2 keys x 2 seeds matrix-game sweep on a local multi-process Ray cluster
(`credit cluster up` on 127.0.0.1) that survives one trial's process killed with kill -9,
is resumed by the same command, and ranks the configurations."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from cluster.cli import main
from tests.cluster.polling import wait_for
from tests.cluster.test_repro_cluster import _credit, _free_port

tune = pytest.importorskip("ray.tune", reason="credit sweep needs ray[tune]")
from cluster.repro import sweep as tune_sweep  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SWEEP = ["sweep", "--algo", "vdn", "--env", "matrix/two_step", "--t-max", "300"]
SWEEP += ["--grid", "algo.lr=0.0005,0.005", "--grid", "algo.agent.hidden=32,64", "--seeds", "2"]
SWEEP += ["--bootstrap-reps", "100"]


def test_points_cross_the_grid_and_draw_the_random_keys_with_tune():
    grid = {"algo.lr": [0.001, 0.01], "algo.agent.hidden": [32, 64]}
    assert tune_sweep.points(grid, {}, 4, 0) == [
        {"algo.lr": 0.001, "algo.agent.hidden": 32},
        {"algo.lr": 0.001, "algo.agent.hidden": 64},
        {"algo.lr": 0.01, "algo.agent.hidden": 32},
        {"algo.lr": 0.01, "algo.agent.hidden": 64},
    ]
    random = {"algo.lr": tune.loguniform(1e-4, 1e-2), "algo.gamma": tune.choice([0.9, 0.99])}
    drawn = tune_sweep.points({"run.num_envs": [1, 2]}, random, 3, 5)
    assert len(drawn) == 6 and drawn == tune_sweep.points({"run.num_envs": [1, 2]}, random, 3, 5)
    assert all(1e-4 <= p["algo.lr"] <= 1e-2 and p["algo.gamma"] in (0.9, 0.99) for p in drawn)
    assert len({p["algo.lr"] for p in drawn}) == 6
    sweep = tune_sweep.Sweep("vdn", "matrix/two_step", (), ("run.t_max=10",), tuple(drawn), 2)
    trials = sweep.trials()
    assert [t["name"] for t in trials[:3]] == ["p000_s0", "p000_s1", "p001_s0"]
    argv = sweep.argv(trials[1], Path("o"))
    assert argv[:4] == ["train", "--out", "o", "--seed"] and argv[4] == "1"
    assert f"algo.lr={drawn[0]['algo.lr']}" in argv and "run.t_max=10" in argv


@pytest.mark.parametrize(
    "argv, message",
    [
        ([], "name at least one key to search"),
        (["--grid", "algo.lr"], "--grid takes KEY=V1,V2"),
        (["--uniform", "algo.lr=1,2,3"], "--uniform takes KEY=LOW,HIGH"),
        (["--grid", "algo.nope=1,2"], "unknown config key algo.nope"),
        (["--grid", "algo.lr=1,2", "--seeds", "0"], "--seeds must be >= 1"),
    ],
)
def test_bad_input_exits_2_before_any_trial(tmp_path, capsys, argv, message):
    base = ["sweep", "--algo", "vdn", "--env", "matrix/two_step", "--out", str(tmp_path / "o")]
    assert main([*base, *argv]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.fixture
def env(tmp_path):
    return {**os.environ, "CREDIT_STATE_DIR": str(tmp_path / "state"), "PYTHONUNBUFFERED": "1"}


def _started(text: str) -> list[tuple[str, int]]:
    return [
        (n, int(p)) for n, p in re.findall(r"trial (p\d+_s\d) started on \S+ \(pid (\d+)\)", text)
    ]


def _driver(command: list[str], env: dict, log_path: Path) -> subprocess.Popen:
    log = open(log_path, "w")  # noqa: SIM115 - the child holds it; closed when the test ends
    argv = [sys.executable, "-m", "cluster.cli", *command]
    return subprocess.Popen(argv, cwd=ROOT, env=env, stdout=log, stderr=log)


@pytest.mark.slow
def test_sweep_on_a_local_cluster_resumes_and_survives_a_killed_trial(tmp_path, env):
    """Ctrl-C of the driver with trials still to run, then the same command again: the
    finished trials are kept and the rest run; during that run one trial's process is
    killed with kill -9 and Tune retries it; the configurations are ranked."""
    port = _free_port()
    up = _credit(["cluster", "up", "--num-cpus", "2", "--port", str(port)], env, timeout=180)
    assert up.returncode == 0, up.stderr[-2000:]
    out = tmp_path / "sweep"
    command = [*SWEEP, "--out", str(out), "--address", "auto"]
    trials = out / "trials"

    def done() -> set[str]:
        return {p.parent.name for p in trials.glob("*/summary.json")} if trials.exists() else set()

    first_log, second_log = tmp_path / "first.log", tmp_path / "second.log"
    try:
        driver = _driver(command, env, first_log)
        try:
            wait_for(
                lambda: len(done()) >= 2,
                timeout_s=300,
                what="2 trials",
                proc=driver,
                log=first_log,
            )
            driver.send_signal(signal.SIGINT)  # Ctrl-C: Tune saves its state and stops
            driver.wait(timeout=120)
        finally:
            if driver.poll() is None:
                driver.kill()
        assert "joined Ray cluster at 127.0.0.1:" in first_log.read_text()
        kept = done()
        assert 2 <= len(kept) < 8, kept  # interrupted with trials still to run
        # The same command again: Tune's experiment is restored and only the rest run.
        driver = _driver(command, env, second_log)
        try:
            victim, pid = wait_for(
                lambda: next(iter(_started(second_log.read_text())), None),
                timeout_s=240,
                what="a trial's start in the resumed sweep",
                proc=driver,
                log=second_log,
            )
            metrics = trials / victim / "metrics.jsonl"
            wait_for(
                lambda: metrics.exists() and metrics.read_text().strip(),
                timeout_s=120,
                what=f"{victim}'s first evaluation",
                proc=driver,
                log=second_log,
            )
            os.kill(pid, signal.SIGKILL)  # the Ray worker process running the trial
            assert driver.wait(timeout=600) == 0, second_log.read_text()[-3000:]
        finally:
            if driver.poll() is None:
                driver.kill()
        text = second_log.read_text()
        assert "resuming the sweep" in text
        started = _started(text)
        assert not {n for n, _ in started} & kept, (started, kept)  # kept, not retrained
        retried = [p for n, p in started if n == victim]
        assert len(retried) >= 2 and retried[-1] != pid  # Tune retried it in a new process
        result = json.loads((out / "sweep.json").read_text())
        ranking = result["ranking"]
        assert len(ranking) == 4 and [r["rank"] for r in ranking] == [1, 2, 3, 4]
        assert all(r["runs"] == 2 and r["missing"] == 0 for r in ranking)
        iqms = [r["iqm"] for r in ranking]
        assert iqms == sorted(iqms, reverse=True)
        assert all(r["ci"][0] <= r["iqm"] <= r["ci"][1] for r in ranking)
        assert {json.dumps(r["config"], sort_keys=True) for r in ranking} == {
            json.dumps({"algo.lr": lr, "algo.agent.hidden": h}, sort_keys=True)
            for lr in (0.0005, 0.005)
            for h in (32, 64)
        }
        assert len(done()) == 8
        for trial in trials.iterdir():  # credit train's outputs, whole
            summary = json.loads((trial / "summary.json").read_text())
            assert summary["t_env"] >= 300 and (trial / "checkpoint" / "learner.pt").exists()
            rows = (trial / "metrics.jsonl").read_text().splitlines()
            assert [json.loads(x)["t_env"] for x in rows][-1] == summary["t_env"]
        assert "rank  IQM test_return_mean" in text
    finally:
        down = _credit(["cluster", "down"], env, timeout=120)
        assert down.returncode == 0, down.stderr[-2000:]
