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


def test_a_credit_process_sets_a_passive_wait_with_a_short_spin_before_torch_loads():
    """Every entry point (`credit`, Ray workers running our functions) imports the package
    `cluster` before any of its modules, and so before they import torch."""
    code = "import os, sys, cluster; e = os.environ.get; "
    code += "print(e('OMP_WAIT_POLICY'), e('GOMP_SPINCOUNT'), 'torch' in sys.modules)"
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}

    def run(**extra: str) -> list[str]:
        out = subprocess.run(
            [sys.executable, "-c", code], env={**env, **extra}, capture_output=True, text=True
        )
        return out.stdout.split() or [out.stderr]

    assert run() == ["PASSIVE", cpu.SHORT_SPIN, "False"]
    assert run(GOMP_SPINCOUNT="0") == ["PASSIVE", "0", "False"]  # a user's spin stays
    # a user's own policy decides the spin too: none is added to it
    assert run(OMP_WAIT_POLICY="ACTIVE") == ["ACTIVE", "None", "False"]
    assert run(OMP_WAIT_POLICY="PASSIVE") == ["PASSIVE", "None", "False"]


@pytest.mark.parametrize(
    "policy, count, spins",
    [
        ("PASSIVE", None, False),
        ("PASSIVE", "0", False),
        ("PASSIVE", "10000", True),
        ("passive", "10k", True),
        ("PASSIVE", "infinite", True),
        ("PASSIVE", "lots", False),  # libgomp ignores it and keeps PASSIVE's 0
        ("ACTIVE", None, True),
        (None, None, True),  # libgomp's own default spins
    ],
)
def test_spinning_reads_the_wait_as_libgomp_does(monkeypatch, policy, count, spins):
    for name, value in (("OMP_WAIT_POLICY", policy), ("GOMP_SPINCOUNT", count)):
        if value is None:
            monkeypatch.delenv(name, raising=False)
        else:
            monkeypatch.setenv(name, value)
    assert cpu.spinning() is spins


def test_a_fixed_count_on_a_busy_machine_warns_when_threads_spin(
    keep_torch_threads, monkeypatch, caplog
):
    monkeypatch.setattr(cpu, "busy_elsewhere", lambda: 2.0)
    monkeypatch.setenv("OMP_WAIT_POLICY", "PASSIVE")
    monkeypatch.setenv("GOMP_SPINCOUNT", cpu.SHORT_SPIN)
    with caplog.at_level("WARNING", logger="cluster.cpu"):
        cpu.ThreadGovernor(2)
    assert "torch threads fixed at 2 while other processes keep about 2.0 CPUs busy" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="cluster.cpu"):
        cpu.ThreadGovernor(1)  # one thread has no team to wait for
        monkeypatch.setenv("GOMP_SPINCOUNT", "0")
        cpu.ThreadGovernor(2)  # threads that sleep at once
        monkeypatch.setattr(cpu, "busy_elsewhere", lambda: 0.2)
        monkeypatch.setenv("GOMP_SPINCOUNT", cpu.SHORT_SPIN)
        cpu.ThreadGovernor(2)  # a quiet machine
    assert caplog.text == ""


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
