"""`credit repro ... --address auto` on a real local multi-process Ray cluster (`credit cluster
up --num-cpus 2` on 127.0.0.1, torn down after): the same numbers as without --address, a pair
whose worker process is killed is retried and the output is whole and the same.

Slow (about 3 minutes on the 2-core machine): it starts a Ray cluster and five repro runs."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tests.cluster.polling import wait_for

pytest.importorskip("ray", reason="repro --address needs ray")
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
MATRIX = ["repro", "matrix", "--algos", "vdn,qmix", "--games", "matrix/two_step"]
MATRIX += ["--seeds", "3", "--t-max", "400"]
SMAC = ["repro", "smac", "--algos", "vdn", "--envs", "skirmish/3m", "--seeds", "2"]
SMAC += ["--t-max", "200", "--test-interval", "100", "--set", "run.test_episodes=2"]
SMAC += ["--set", "replay.batch_size=4", "--checkpoints"]


def _credit(args: list[str], env: dict, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "cluster.cli", *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=kw.pop("timeout", 300),
        **kw,
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _without_wall(d):
    """The JSON without its wall-clock times (never the same twice): every wall_s, and the
    curves' wall (seconds at each evaluation)."""
    if isinstance(d, dict):
        return {k: _without_wall(v) for k, v in d.items() if k not in ("wall_s", "wall")}
    if isinstance(d, list):
        return [_without_wall(x) for x in d]
    return d


def _assert_same_results(a: Path, b: Path) -> None:
    """summary.json, curves.json and every evals/*.jsonl equal but for the wall times."""
    for name in ("summary.json", "curves.json"):
        left, right = (json.loads((d / name).read_text()) for d in (a, b))
        assert _without_wall(left) == _without_wall(right), name
    logs = sorted(p.name for p in (a / "evals").glob("*.jsonl"))
    assert logs and logs == sorted(p.name for p in (b / "evals").glob("*.jsonl"))
    for name in logs:
        left, right = (
            [_without_wall(json.loads(x)) for x in (d / "evals" / name).read_text().splitlines()]
            for d in (a, b)
        )
        assert left and left == right, name


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    state = tmp_path_factory.mktemp("state")
    return {**os.environ, "CREDIT_STATE_DIR": str(state), "PYTHONUNBUFFERED": "1"}


@pytest.fixture(scope="module")
def local_matrix(tmp_path_factory, env):
    """The matrix reproduction without --address (two local worker processes)."""
    out = tmp_path_factory.mktemp("local") / "matrix"
    done = _credit([*MATRIX, "--out", str(out)], env)
    assert done.returncode == 0, done.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def cluster(env):
    """`credit cluster up --num-cpus 2` on 127.0.0.1 for this module; `down` after."""
    port = _free_port()
    up = _credit(["cluster", "up", "--num-cpus", "2", "--port", str(port)], env, timeout=180)
    assert up.returncode == 0, up.stderr[-2000:]
    try:
        yield f"127.0.0.1:{port}"
    finally:
        down = _credit(["cluster", "down"], env, timeout=120)
        assert down.returncode == 0, down.stderr[-2000:]


def test_matrix_on_the_cluster_gives_the_local_numbers(tmp_path, env, cluster, local_matrix):
    out = tmp_path / "matrix"
    done = _credit([*MATRIX, "--out", str(out), "--address", "auto"], env)
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"joined Ray cluster at {cluster}; 2 pairs as Ray tasks" in done.stderr
    for algo in ("vdn", "qmix"):
        assert re.search(rf"pair {algo}@matrix/two_step started on \S+ \(pid \d+\)", done.stderr)
        assert re.search(rf"pair {algo}@matrix/two_step finished in \d+ s", done.stderr)
    _assert_same_results(local_matrix, out)


def test_a_killed_pair_is_retried_and_the_output_is_whole(tmp_path, env, cluster, local_matrix):
    """The retry continues from the pair's last checkpoint (on this one machine, the node
    that runs it can read it) and the output is the one of a run that was not interrupted."""
    out = tmp_path / "matrix"
    log_path = tmp_path / "driver.log"
    cmd = [*MATRIX, "--out", str(out), "--address", "auto", "--checkpoint-every", "100"]
    with open(log_path, "w") as log:
        driver = subprocess.Popen(
            [sys.executable, "-m", "cluster.cli", *cmd],
            cwd=ROOT,
            env=env,
            stdout=log,
            stderr=log,
        )
        try:
            started = re.compile(r"pair vdn@matrix/two_step started on \S+ \(pid (\d+)\)")
            pid = wait_for(
                lambda: (m := started.search(log_path.read_text())) and int(m.group(1)),
                timeout_s=180,
                what="the vdn pair's start",
                proc=driver,
                log=log_path,
            )
            wait_for(
                lambda: (out / "resume" / "matrix-two_step__vdn" / "pair.json").exists(),
                timeout_s=120,
                what="the vdn pair's first checkpoint",
                proc=driver,
                log=log_path,
            )
            os.kill(pid, signal.SIGKILL)  # the Ray worker process running the pair
            assert driver.wait(timeout=300) == 0, log_path.read_text()[-3000:]
        finally:
            if driver.poll() is None:
                driver.kill()
    text = log_path.read_text()
    assert "pair vdn@matrix/two_step restarted on" in text and "attempt 2" in text
    assert "pair vdn@matrix/two_step resumed from its checkpoint at t_env" in text
    assert "pair qmix@matrix/two_step restarted" not in text
    _assert_same_results(local_matrix, out)


def test_a_curves_experiment_with_checkpoints_on_the_cluster(tmp_path, env, cluster):
    """`credit repro smac --checkpoints`: the pair's checkpoint comes back into the driver's
    --out, the same as without --address."""
    local, remote = tmp_path / "local", tmp_path / "remote"
    done = _credit([*SMAC, "--out", str(local), "--workers", "1"], env)
    assert done.returncode == 0, done.stderr[-3000:]
    done = _credit([*SMAC, "--out", str(remote), "--address", "auto"], env)
    assert done.returncode == 0, done.stderr[-3000:]
    _assert_same_results(local, remote)
    ckpt = Path("checkpoints") / "skirmish-3m__vdn" / "learner.pt"
    assert (local / ckpt).read_bytes() == (remote / ckpt).read_bytes()
