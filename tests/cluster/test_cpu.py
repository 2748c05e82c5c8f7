"""cluster.cpu and `credit bench load`: threads that sleep, an "auto" torch thread count that
follows the CPUs other processes keep busy, and the load generator that makes them busy."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from cluster import cpu
from cluster.bench.load import LoadGenerator
from cluster.cli import main
from cluster.config.schema import ConfigError
from cluster.config.train import load_train_config
from tests.cluster.polling import wait_for

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def keep_torch_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_a_credit_process_sets_a_passive_wait_policy_before_torch_loads():
    """Every entry point (`credit`, Ray workers running our functions) imports the package
    `cluster` before any of its modules, and so before they import torch."""
    code = "import os, sys, cluster; print(os.environ['OMP_WAIT_POLICY'], 'torch' in sys.modules)"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.stdout.split() == ["PASSIVE", "False"], out.stderr
    env["OMP_WAIT_POLICY"] = "ACTIVE"  # a user's own setting stays
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.stdout.split() == ["ACTIVE", "False"], out.stderr


def test_busy_processes_are_counted_and_auto_leaves_them_their_cpus():
    """With one spinning process per usable CPU, `busy_elsewhere` counts at least that many
    and "auto" takes one thread (the least it takes); without them this process's own
    threads are never counted."""
    usable = cpu.usable_cpus()
    with LoadGenerator(procs=usable, seconds=60):
        wait_for(lambda: cpu.busy_elsewhere() >= usable, timeout_s=30, what="the busy processes")
        assert cpu.auto_threads() == 1
    assert cpu.auto_threads(limit=1) == 1


def test_governor_keeps_a_fixed_count_and_measures_auto_again(keep_torch_threads, monkeypatch):
    fixed = cpu.ThreadGovernor(2, every_s=0.0)
    fixed.tick()
    assert torch.get_num_threads() == 2 and fixed.used == [2]
    busy = iter([3.0, 0.0])  # readings of the other processes' demand, in turn
    monkeypatch.setattr(cpu, "usable_cpus", lambda: 4)
    monkeypatch.setattr(cpu, "busy_elsewhere", lambda: next(busy))
    auto = cpu.ThreadGovernor(0, every_s=0.0)
    assert torch.get_num_threads() == 1
    auto.tick()
    assert torch.get_num_threads() == 4 and auto.used == [1, 4]


def test_torch_threads_takes_0_for_auto_and_refuses_negatives():
    assert load_train_config("vdn", "matrix/two_step", [], ["run.torch_threads=0"])
    with pytest.raises(ConfigError, match="torch_threads must be >= 1, or 0 for auto"):
        load_train_config("vdn", "matrix/two_step", [], ["run.torch_threads=-1"])


def test_bench_load_keeps_the_cpus_busy_and_reports_it(tmp_path, capsys):
    out = tmp_path / "load.json"
    assert main(["bench", "load", "--procs", "1", "--seconds", "2", "--out", str(out)]) == 0
    got = json.loads(out.read_text())
    assert got["benchmark"] == "load" and got["procs"] == 1 and len(got["cpu_s"]) == 1
    assert got["cpu_s"][0] > 0
    assert main(["bench", "load", "--procs", "-1"]) == 2
    assert "--procs must be >= 0" in capsys.readouterr().err


@pytest.mark.slow  # two short `credit bench learn` processes, about 40 s
def test_bench_learn_compare_load_prints_both_and_the_slowdown(tmp_path):
    out = tmp_path / "compare.json"
    argv = [sys.executable, "-m", "cluster.cli", "bench", "learn", "--env", "skirmish/3m"]
    argv += ["--algo", "vdn", "--seeds", "1", "--t-max", "300", "--test-interval", "300"]
    argv += ["--set", "run.test_episodes=2", "--set", "replay.batch_size=4"]
    argv += ["--compare-load", "--load-procs", "1", "--out", str(out)]
    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    got = json.loads(out.read_text())
    assert got["benchmark"] == "learn_compare_load" and got["load_procs"] == 1
    assert got["load_cpu_s"][0] > 0
    for side in ("quiet", "loaded"):
        assert got[side]["benchmark"] == "learn" and got[side]["t_env_end"] >= 300
        assert got[side]["torch_threads"] == "auto" and min(got[side]["threads_used"]) >= 1
    assert got["slowdown_wall_per_env_step"] > 0
