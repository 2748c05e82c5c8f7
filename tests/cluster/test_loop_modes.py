"""Local mode against cluster mode with one actor, through the real things (slow tier; the
default tier's comparison is tests/cluster/test_cluster_mode.py): `credit train` in both
modes, a private Ray instance on 127.0.0.1, the buffer service over TCP. Both modes leave
their tables in the buffer service's snapshot format (cluster: OUT/buffer/data; local: the
checkpoint's buffer/member-0), which is where the episodes are compared."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.cluster.episodes import assert_same_first_episodes

pytest.importorskip("ray", reason="cluster mode needs ray")


@pytest.fixture
def env(tmp_path):
    return {
        **os.environ,
        "CREDIT_STATE_DIR": str(tmp_path / "state"),
        "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
        "RAY_AUTH_MODE": "token",
    }


def _train(mode: str, out: Path, env: dict, seed: int, t_max: int, *args: str) -> dict:
    cmd = [sys.executable, "-m", "cluster.cli", "train", "--mode", mode, "--out", str(out)]
    cmd += ["--seed", str(seed), "--t-max", str(t_max), *args]
    cmd += ["--set", "replay.capacity=100000", "--set", "cluster.metrics=false"]
    if mode == "cluster":
        cmd += ["--actors", "1"]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads((out / "summary.json").read_text())


# slow (about 60 s): a seeded, stochastic env; `make test` compares the modes on a matrix game
# (tests/cluster/test_cluster_mode.py::test_cluster_outputs_match_local_mode).
@pytest.mark.slow
def test_one_actor_cluster_run_collects_the_episodes_local_mode_collects_on_skirmish(tmp_path, env):
    """Same seed, same episodes on a map whose envs draw random numbers: every episode acted
    with the initial weights (version 0, all of them until the first update) is the same in
    both modes (cluster actors used to seed their envs from the wall clock)."""
    args = ["--algo", "qmix", "--env", "skirmish/3m", "--set", "replay.batch_size=8"]
    args += ["--set", "run.test_episodes=1"]
    local = _train("local", tmp_path / "local", env, 3, 600, *args)
    remote = _train("cluster", tmp_path / "cluster", env, 3, 600, *args)
    assert local["updates"] > 0 and remote["updates"] > 0
    assert_same_first_episodes(
        tmp_path / "local" / "checkpoint" / "buffer" / "member-0",
        tmp_path / "cluster" / "buffer" / "data",
        at_least=8,
    )


def _final_return(out: Path, last: int) -> float:
    lines = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines() if x]
    return float(np.mean([x["test_return_mean"] for x in lines[-last:]]))


# slow (about 4 min on the shared 2-core box): three seeds of each mode.
@pytest.mark.slow
def test_learning_curves_of_both_modes_agree_within_noise_over_three_seeds(tmp_path, env):
    """QMIX on matrix/two_step (optimum 8; 7 is the trap), 3 seeds per mode: the mean of
    the last evaluations is within noise between modes, and both learned (an untrained or
    stalled learner stays far below)."""
    args = ["--algo", "qmix", "--env", "matrix/two_step", "--set", "run.test_interval=20"]
    finals = {"local": [], "cluster": []}
    for seed in range(3):
        for mode in finals:
            out = tmp_path / f"{mode}{seed}"
            summary = _train(mode, out, env, seed, 1200, *args)
            assert summary["t_env"] >= 1200 and summary["updates"] > 0
            finals[mode].append(_final_return(out, last=10))
    local, cluster = np.mean(finals["local"]), np.mean(finals["cluster"])
    assert min(local, cluster) >= 7.3, finals  # both learned (8 in most seeds, not the 7 trap)
    assert abs(local - cluster) <= 0.7, finals
