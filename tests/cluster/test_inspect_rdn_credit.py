"""`credit inspect rdn-credit`: RDN trained with its own-action credit measured at every
evaluation (results/smac/README.md cites it for why the dissertation's recipe collapses)."""

import json

import pytest

from cluster.cli import main


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seeds", "0"], "--seeds must be >= 1"),
        (["--env", "skirmish/nope"], "unknown env 'skirmish/nope'"),
        (["--t-max", "0"], "t_max must be >= 1"),
    ],
)
def test_bad_arguments_exit_2(tmp_path, capsys, argv, message):
    out = tmp_path / "credit.jsonl"
    assert main(["inspect", "rdn-credit", *argv, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow
def test_tiny_run_writes_one_measured_line_per_evaluation(tmp_path, capsys):
    out = tmp_path / "why" / "credit.jsonl"
    argv = ["inspect", "rdn-credit", "--env", "skirmish/3m", "--seeds", "2", "--t-max", "400"]
    argv += ["--set", "run.test_interval=200", "--set", "replay.batch_size=4"]
    assert main([*argv, "--set", "run.test_episodes=2", "--out", str(out)]) == 0
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    printed = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert rows == printed and len(rows) >= 2
    assert rows[-1]["t_env"] >= 400 and rows[-1]["updates"] > 0
    assert all(len(r["won"]) == 2 for r in rows)
    last = rows[-1]  # the replay holds a batch by then: the credit is measured
    assert last["swaps"] > 0 and 0.0 <= last["argmax_agreement"] <= 1.0
    assert 0.0 <= last["agent_argmax_agreement"] <= 1.0
    assert last["mean_abs_dq"] >= 0.0 and last["mean_abs_dr_obs"] >= 0.0
