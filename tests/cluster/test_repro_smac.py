"""`credit repro smac` and `credit bench learn`: tiny end-to-end runs and their bad input."""

import json

import pytest

from cluster.cli import main


def test_tiny_repro_smac_writes_summary_with_steps_to_95_and_plots(tmp_path, capsys):
    out = tmp_path / "smac"
    argv = ["repro", "smac", "--envs", "skirmish/3m", "--algos", "vdn,rdn", "--seeds", "2"]
    argv += ["--t-max", "600", "--test-interval", "300", "--out", str(out), "--workers", "1"]
    argv += ["--set", "run.test_episodes=2", "--set", "replay.batch_size=4"]
    assert main([*argv, "--bootstrap-reps", "50"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["skirmish/3m"]) == {"vdn", "rdn"}
    keys = {
        "steps_to_50",
        "steps_to_80",
        "steps_to_95",
        "steps_to_50_smoothed",
        "steps_to_80_smoothed",
        "steps_to_95_smoothed",
        "median_win_rate_last10",
        "mean_win_rate_last10",
        "seeds",
        "t_env",
        "wall_s",
    }
    for cell in summary["skirmish/3m"].values():
        assert keys <= set(cell)
        assert cell["seeds"] == 2 and cell["t_env"] >= 600
    assert (out / "smac_3m.png").stat().st_size > 0
    rows = [json.loads(x) for x in (out / "evals" / "skirmish-3m__rdn.jsonl").open()]
    assert len(rows) >= 3 and all(len(r["won"]) == 2 for r in rows)
    assert "loss_critic" in rows[-1] and "q_tot_mean" in rows[-1]  # RDN's diagnostics
    vdn = [json.loads(x) for x in (out / "evals" / "skirmish-3m__vdn.jsonl").open()]
    assert "q_taken_mean" in vdn[-1] and "loss_td" in vdn[-1]
    assert "steps to 50/80/95%" in capsys.readouterr().out


@pytest.fixture
def keep_torch_threads():
    """bench learn sets this process's torch threads; put them back for later tests."""
    import torch

    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_bench_learn_reports_each_seed_and_the_load(tmp_path, capsys, keep_torch_threads):
    from cluster.cpu import usable_cpus

    out = tmp_path / "learn.json"
    argv = ["bench", "learn", "--env", "skirmish/3m", "--algo", "vdn", "--seeds", "2"]
    argv += ["--target-win", "1.0", "--t-max", "500", "--test-interval", "250"]
    argv += ["--set", "run.test_episodes=2", "--set", "replay.batch_size=4", "--out", str(out)]
    assert main(argv) == 0
    got = json.loads(out.read_text())
    assert len(got["env_steps"]) == 2 and len(got["wall_s"]) == 2
    for steps, wall in zip(got["env_steps"], got["wall_s"], strict=True):
        assert (steps is None) == (wall is None)
        assert steps is None or steps <= got["t_env_end"]
    assert got["t_env_end"] >= 500 or all(s is not None for s in got["env_steps"])
    assert {"min", "mean", "max"} <= set(got["load_avg_1m"])
    assert all(len(c["won"]) == 2 for c in got["curve"])
    assert json.loads(capsys.readouterr().out)["benchmark"] == "learn"
    # "auto" unless told otherwise: the usable CPUs less those busy elsewhere, at least 1
    assert got["torch_threads"] == "auto" and got["omp_wait_policy"] == "PASSIVE"
    assert all(1 <= n <= usable_cpus() for n in got["threads_used"])
    assert got["machine"]["torch_threads"] == got["threads_used"][-1]
    argv += ["--threads", "1", "--t-max", "250"]
    assert main(argv) == 0
    got = json.loads(out.read_text())
    assert got["torch_threads"] == 1 == got["machine"]["torch_threads"]
    assert got["threads_used"] == [1]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["bench", "learn", "--target-win", "1.5"], "--target-win must be in (0, 1]"),
        (["bench", "learn", "--threads", "-1"], "--threads must be >= 0"),
        (["bench", "learn", "--env", "matrix/two_step"], "reports no battle wins"),
        (["bench", "learn", "--algo", "dqn"], "unknown algorithm 'dqn'"),
        (["bench", "update", "--algos", "vdn,dqn"], "unknown algorithm 'dqn'"),
        (["bench", "update", "--profile", "-1"], "--profile must be >= 0, got -1"),
        (
            ["bench", "update", "--algos", "vdn,rdn", "--set", "vdn:run.keep_freed_memory=false"],
            "run.keep_freed_memory must be the same for every algorithm",
        ),
        (["repro", "smac", "--out", "x", "--algos", "qmix,nope"], "unknown algorithm 'nope'"),
    ],
)
def test_bad_input_exits_2(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_bench_update_times_algorithms_side_by_side(capsys):
    # in-process: leave this test session's allocator alone (tests/cluster/test_alloc.py)
    argv = ["bench", "update", "--env", "skirmish/3m", "--algos", "vdn,rdn", "--batch", "4"]
    argv += ["--set", "run.keep_freed_memory=false"]
    assert main([*argv, "--rounds", "1", "--updates", "1"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["keep_freed_memory"] is False
    assert set(got["ms_per_update"]) == {"vdn", "rdn"} and got["ratio_to_vdn"]["vdn"] == 1.0
    assert got["ratio"] == got["ratio_to_vdn"]["rdn"]
    assert set(got["peak_mib_per_update"]) == {"vdn", "rdn"}
    assert "profile" not in got


def test_bench_update_profile_lists_the_costliest_operators(capsys):
    argv = ["bench", "update", "--env", "skirmish/3m", "--algos", "vdn", "--batch", "4"]
    argv += ["--set", "run.keep_freed_memory=false", "--rounds", "1", "--updates", "1"]
    assert main([*argv, "--profile", "4"]) == 0
    rows = json.loads(capsys.readouterr().out)["profile"]["vdn"]
    assert len(rows) == 4 and all(r["op"].startswith("aten::") for r in rows)
    selfs = [r["self_ms"] for r in rows]
    assert selfs == sorted(selfs, reverse=True) and selfs[0] > 0
    assert all(r["calls"] >= 1 for r in rows)
    # shares of the update's operator time: the top four cannot exceed all of it
    assert 0 < sum(r["share"] for r in rows) <= 1.0
    assert rows[0]["share"] >= rows[-1]["share"] > 0
