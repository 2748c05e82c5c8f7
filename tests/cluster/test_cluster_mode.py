"""`credit train --mode cluster` with real processes: a private Ray instance on 127.0.0.1,
Ray rollout actors, the buffer service over TCP, and kill -9 of each part."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from buffer_service.config import BufferConfig, TableConfig
from buffer_service.state import BufferState
from buffer_service.storage import Storage
from cluster.launch import ray_cluster
from tests.cluster.episodes import assert_same_first_episodes
from tests.cluster.polling import wait_for
from tests.cluster.test_run_loggers import assert_event_files_match_metrics

ray = pytest.importorskip("ray", reason="cluster mode needs ray")

BASE = ["--algo", "vdn", "--env", "matrix/two_step", "--mode", "cluster", "--actors", "2"]
BIG_REPLAY = ["--set", "replay.capacity=100000"]  # keep every episode for inspection


@pytest.fixture
def env(tmp_path):
    return {**os.environ, "CREDIT_STATE_DIR": str(tmp_path / "state"), "PYTHONUNBUFFERED": "1"}


def _cli(args):
    return [sys.executable, "-m", "cluster.cli", "train", *args]


def _start(args, env, out: Path) -> subprocess.Popen:
    log = open(out.parent / f"{out.name}.log", "w")  # noqa: SIM115 - closed with the process
    return subprocess.Popen(_cli([*args, "--out", str(out)]), env=env, stdout=log, stderr=log)


def _progress(out: Path) -> int:
    path = out / "metrics.jsonl"
    if not path.exists():
        return 0
    lines = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    return lines[-1]["t_env"] if lines else 0


def _stored_episodes(out: Path):
    state = BufferState(
        BufferConfig(tables=(TableConfig(name="replay", kind="replay", capacity=100000),))
    )
    Storage(str(out / "buffer" / "data")).restore(state)
    return state


def _assert_whole_and_unique(state, in_flight: int = 0):
    """Every stored episode whole, under its own key. `in_flight`: inserts a crash of the
    service may have cut between storing and acknowledging; their retries are duplicates."""
    assert state.duplicates <= in_flight
    for (actor, seq), ep in state.episodes.items():
        assert ep.key == (actor, seq)
        assert ep.length == 2 and bool(ep.terminated[-1]) and ep.filled.all()  # whole episodes


@pytest.mark.default_tier(reason="the default tier's cluster run")
def test_cluster_outputs_match_local_mode(tmp_path, env):
    """A one-actor cluster run and a local run with the same seed: the same outputs (every
    summary key of local mode, metrics lines, checkpoint), and the same episodes for the
    first rounds (all 16 acted with the initial weights, before the first update), compared
    field by field in the two buffer folders (the service's, the local checkpoint's)."""
    common = ["--algo", "vdn", "--env", "matrix/two_step", "--seed", "3", "--t-max", "100"]
    common += [*BIG_REPLAY, "--set", "replay.batch_size=16"]
    common += ["--set", "run.loggers=[jsonl,tensorboard]"]
    runs = {}
    for mode in ("local", "cluster"):
        out = tmp_path / mode
        args = [*common, "--mode", mode, "--out", str(out)]
        args += ["--actors", "1"] if mode == "cluster" else []
        done = subprocess.run(_cli(args), env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-3000:]
        runs[mode] = json.loads((out / "summary.json").read_text())
    local, summary = runs["local"], runs["cluster"]
    assert set(local) <= set(summary)
    assert summary["mode"] == "cluster" and summary["t_env"] >= 100 and summary["updates"] > 0
    out = tmp_path / "cluster"
    lines = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert lines and all(
        {"t_env", "episode", "test_return_mean", "wall_s"} <= set(x) for x in lines
    )
    # run.loggers: the same event files in both modes, matching each run's metrics.jsonl
    tags = [set(assert_event_files_match_metrics(tmp_path / m)) for m in ("local", "cluster")]
    assert tags[0] == tags[1]
    targets = json.loads((out / "targets.json").read_text())
    assert len(targets[0]["targets"]) == 3  # learner, the actor, buffer service
    assert all(t.startswith("127.0.0.1:") for t in targets[0]["targets"])
    _assert_whole_and_unique(_stored_episodes(out))
    assert_same_first_episodes(
        tmp_path / "local" / "checkpoint" / "buffer" / "member-0", out / "buffer" / "data", 16
    )


# slow (about 45 s): make test keeps the value family's cluster runs; this is EM-CAC's two tables.
@pytest.mark.slow
def test_emcac_trains_in_cluster_mode_on_both_tables(tmp_path, env):
    """EM-CAC in cluster mode: every learner step takes its 32 cycling episodes and its 32
    replay episodes for the extra critic pass from the buffer service, and no sample of the
    cycling table is spent on a step that did not happen."""
    from cluster.config.plan import data_plan
    from cluster.config.train import load_train_config

    out = tmp_path / "run"
    args = ["--algo", "emcac", "--env", "skirmish/3m", "--mode", "cluster", "--actors", "2"]
    args += ["--t-max", "1500", "--set", "run.test_episodes=2", "--out", str(out)]
    done = subprocess.run(_cli(args), env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    updates = json.loads((out / "summary.json").read_text())["updates"]
    assert updates > 0
    plan = data_plan(load_train_config("emcac", "skirmish/3m"), actors=2)
    state = BufferState(BufferConfig(tables=plan.tables))
    Storage(str(out / "buffer" / "data")).restore(state)
    tables = state.stats()["tables"]
    assert tables["cycling"]["samples"] == 32 * updates
    # at most one extra batch sampled and still waiting for its cycling batch at shutdown
    assert tables["replay"]["samples"] in (32 * updates, 32 * (updates + 1))
    learner = torch.load(out / "checkpoint" / "learner.pt", weights_only=False)
    assert learner["target_policy"] is not None  # EM-CAC's Polyak policy is checkpointed


@pytest.mark.default_tier(reason="the default tier's cluster kill -9")
def test_kill9_actor_is_restarted_and_buffer_stays_whole(tmp_path, env):
    out = tmp_path / "run"
    proc = _start([*BASE, "--t-max", "600", *BIG_REPLAY], env, out)
    try:
        wait_for(lambda: _progress(out) >= 60, 240, "training progress", proc)
        victim = json.loads((out / "cluster.json").read_text())["actors"][0]
        killed_at_us = time.time_ns() // 1000
        os.kill(victim["pid"], signal.SIGKILL)
        assert proc.wait(timeout=300) == 0, (out.parent / "run.log").read_text()[-3000:]
    finally:
        proc.kill()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["actor_restarts"] >= 1 and summary["t_env"] >= 600
    after = json.loads((out / "cluster.json").read_text())["actors"][0]
    assert after["pid"] != victim["pid"]
    state = _stored_episodes(out)
    _assert_whole_and_unique(state)
    new_life = [
        seq for actor, seq in state.episodes if actor == victim["actor_id"] and seq > killed_at_us
    ]
    assert new_life, "the restarted actor inserted nothing"


def _scrape_inserts(port: int) -> float:
    from urllib.request import urlopen

    text = urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    for line in text.splitlines():
        if line.startswith('credit_buffer_inserts_total{table="replay"}'):
            return float(line.split()[-1])
    return 0.0


# slow (about 65 s): a fault test; make test keeps the actor's kill -9.
@pytest.mark.slow
def test_kill9_buffer_service_restarts_without_losing_acked_episodes(tmp_path, env):
    out = tmp_path / "run"
    proc = _start([*BASE, "--t-max", "600", *BIG_REPLAY], env, out)
    try:
        wait_for(lambda: _progress(out) >= 60, 240, "training progress", proc)
        service = json.loads((out / "cluster.json").read_text())["buffer"]
        acked = _scrape_inserts(service["metrics_port"])  # counted when acknowledged
        os.kill(service["pid"], signal.SIGKILL)
        assert acked > 0
        assert proc.wait(timeout=300) == 0, (out.parent / "run.log").read_text()[-3000:]
    finally:
        proc.kill()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["buffer_restarts"] >= 1 and summary["t_env"] >= 600
    state = _stored_episodes(out)
    assert len(state.episodes) >= acked
    _assert_whole_and_unique(state, in_flight=2)  # one insert (num_envs 1) per actor


def _checkpoint(out: Path):
    path = out / "checkpoint" / "trainer.pt"
    if not path.exists():
        return None
    try:
        return torch.load(path, weights_only=False)
    except (EOFError, RuntimeError, OSError):  # mid-rename; try again
        return None


# slow (about 90 s): a fault test with two cluster runs; make test keeps the actor's kill -9.
@pytest.mark.slow
def test_kill9_learner_then_resume_continues_counters(tmp_path, env):
    out = tmp_path / "run"
    proc = _start([*BASE, "--t-max", "100000", "--set", "run.save_interval=50"], env, out)
    try:
        wait_for(lambda: (c := _checkpoint(out)) and c["t_env"] >= 150, 240, "a checkpoint", proc)
        service_pid = json.loads((out / "cluster.json").read_text())["buffer"]["pid"]
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        proc.kill()
    # The buffer service dies with its launcher (no orphan left serving).
    wait_for(
        lambda: not Path(f"/proc/{service_pid}").exists(), 30, "the orphaned buffer service to exit"
    )
    saved = _checkpoint(out)
    learner = torch.load(out / "checkpoint" / "learner.pt", weights_only=False)
    target = saved["t_env"] + 150
    done = subprocess.run(
        _cli(["--resume", str(out), "--mode", "cluster", "--t-max", str(target)]),
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["t_env"] >= target
    resumed = torch.load(out / "checkpoint" / "learner.pt", weights_only=False)
    assert resumed["updates"] > learner["updates"]
    step = lambda s: float(s["optimiser"]["state"][0]["step"])  # noqa: E731
    assert step(resumed) == step(learner) + (resumed["updates"] - learner["updates"])


# A private Ray instance of another run on the same machine: `credit cluster down` must leave it
# alone (it is answered before and after the down).
BYSTANDER = """
import sys
from cluster.launch.ray_cluster import connect
connect(None, 1)
import ray
one = ray.remote(lambda: 1)
print("ready", ray.get(one.remote()), flush=True)
sys.stdin.readline()
print("after", ray.get(one.remote(), timeout=60), flush=True)
"""


# slow (about 120 s): a whole `credit cluster up`, train, `down` lifecycle.
@pytest.mark.slow
def test_cluster_up_train_with_address_auto_and_down(tmp_path, env):
    """`credit cluster up` starts a Ray head on 127.0.0.1 that `--address auto` joins; `down`
    stops that head's processes and no other Ray instance."""
    bystander = subprocess.Popen(
        [sys.executable, "-c", BYSTANDER],
        env={**env, "CREDIT_STATE_DIR": str(tmp_path / "other")},
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert bystander.stdout.readline().strip() == "ready 1"
    cli = [sys.executable, "-m", "cluster.cli", "cluster"]
    up = subprocess.run(
        [*cli, "up", "--num-cpus", "3", "--port", "6399"],
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert up.returncode == 0, up.stderr[-2000:]
    up_state = (tmp_path / "state" / "cluster" / "state.json").read_text()
    assert ray_cluster.cluster_processes(json.loads(up_state)["pgid"])
    try:
        status = subprocess.run(
            [*cli, "status"], env=env, capture_output=True, text=True, timeout=120
        )
        assert "address: 127.0.0.1:6399" in status.stdout and "3.0 CPU" in status.stdout
        again = subprocess.run(
            [*cli, "up", "--port", "6399"], env=env, capture_output=True, text=True, timeout=120
        )
        assert again.returncode == 2 and "already up" in again.stderr
        out = tmp_path / "run"
        args = [*BASE, "--address", "auto", "--t-max", "100", "--out", str(out)]
        done = subprocess.run(_cli(args), env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-3000:]
        assert "joined Ray cluster at 127.0.0.1:6399" in done.stderr
        assert json.loads((out / "summary.json").read_text())["t_env"] >= 100
    finally:
        down = subprocess.run([*cli, "down"], env=env, capture_output=True, text=True, timeout=120)
    assert down.returncode == 0, down.stderr[-2000:]
    assert "Ray cluster stopped" in down.stdout
    state = json.loads(up_state)
    assert ray_cluster.cluster_processes(state["pgid"]) == []
    from ray._common.utils import get_ray_address_file

    latest = Path(get_ray_address_file(None))  # Ray's "join this head" file, as `ray stop`
    assert not latest.exists() or latest.read_text().strip() != "127.0.0.1:6399"
    status = subprocess.run([*cli, "status"], env=env, capture_output=True, text=True, timeout=60)
    assert "no credit Ray cluster recorded" in status.stdout
    after, _ = bystander.communicate("\n", timeout=120)
    assert after.strip() == "after 1", "cluster down stopped another run's Ray instance"


# slow (45-80 s a case on the shared 2-core box): both cases run in `make test-slow`; the
# learner's schedule is tested in one process by tests/learner/test_schedule.py.
@pytest.mark.slow
@pytest.mark.parametrize("actors, num_envs", [(1, 1), (2, 4)])
def test_updates_and_target_refreshes_per_episode_do_not_depend_on_actors(
    tmp_path, env, actors, num_envs
):
    """replay.updates_per_episode and target_update_episodes mean the same with any number of
    actors and envs per actor: the buffer's rate limiter holds the learner to 2 updates per
    inserted episode, within the in-flight slack (actors x rate_slack rounds), and the target
    network is copied once per 50 episodes."""
    out = tmp_path / "run"
    args = ["--algo", "vdn", "--env", "matrix/two_step", "--mode", "cluster"]
    args += ["--actors", str(actors), "--t-max", "500", "--out", str(out)]
    for kv in (
        f"run.num_envs={num_envs}",
        "replay.updates_per_episode=2",
        "replay.batch_size=4",
        "algo.target_update_episodes=50",
        "run.test_interval=250",
    ):
        args += ["--set", kv]
    done = subprocess.run(_cli(args), env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    episodes, updates = summary["episodes"], summary["updates"]
    # the limiter's slack (actors x rate_slack rounds), one more round per actor counted as
    # the run ends before the learner could sample it, and the first batch's warm-up
    slack = actors * 2 * num_envs + actors * num_envs + 4
    assert 2 * (episodes - slack) <= updates <= 2 * episodes, (episodes, updates)
    learner = torch.load(out / "checkpoint" / "learner.pt", weights_only=False)
    assert episodes // 50 - 1 <= learner["target_epoch"] <= episodes // 50, (episodes, learner)
