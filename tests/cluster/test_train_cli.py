"""`credit train` end to end in one process: outputs, resume, bad input, NaN guard."""

import json

import pytest
import torch
import yaml

from cluster.cli import main


def _train(tmp_path, *extra):
    out = tmp_path / "run"
    code = main(
        [
            "train",
            "--algo",
            "vdn",
            "--env",
            "matrix/two_step",
            "--t-max",
            "200",
            "--out",
            str(out),
            *extra,
        ]
    )
    return code, out


def test_outputs_have_the_documented_form(tmp_path, capsys):
    code, out = _train(tmp_path)
    assert code == 0
    assert "results in" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    for key in (
        "algo",
        "env",
        "seed",
        "t_env",
        "episodes",
        "wall_s",
        "final_test_return_mean",
        "final_test_won_mean",
    ):
        assert key in summary
    assert (
        summary["algo"] == "vdn" and summary["env"] == "matrix/two_step" and summary["t_env"] == 200
    )
    assert summary["final_test_won_mean"] is None  # the matrix games have no wins
    lines = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert len(lines) >= 10
    assert all({"t_env", "episode", "test_return_mean", "wall_s"} <= set(x) for x in lines)
    assert [x["t_env"] for x in lines] == sorted(x["t_env"] for x in lines)
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    assert cfg["algo_name"] == "vdn" and cfg["run"]["t_max"] == 200
    state = torch.load(out / "checkpoint" / "learner.pt", weights_only=False)
    assert state["updates"] == summary["updates"] > 0


def test_resume_continues_counters_and_optimiser(tmp_path):
    code, out = _train(tmp_path)
    assert code == 0
    first = json.loads((out / "summary.json").read_text())
    before = torch.load(out / "checkpoint" / "learner.pt", weights_only=False)
    assert main(["train", "--resume", str(out), "--t-max", "300"]) == 0
    second = json.loads((out / "summary.json").read_text())
    assert second["t_env"] == 300 and second["updates"] > first["updates"]
    assert second["episodes"] == first["episodes"] + 50
    after = torch.load(out / "checkpoint" / "learner.pt", weights_only=False)
    # Adam's step counter continued from the checkpoint rather than restarting at 0.
    step_before = before["optimiser"]["state"][0]["step"]
    step_after = after["optimiser"]["state"][0]["step"]
    assert step_after == step_before + (second["updates"] - first["updates"])
    t_envs = [json.loads(x)["t_env"] for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert t_envs == sorted(t_envs) and t_envs[-1] == 300


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["--algo", "dqn"],
            "valid algorithms: cac, coma, ecac, emcac, iql, mcac, qmix, qmix_ns, rdn, vdn",
        ),
        (["--env", "matrix/nope"], "valid envs:"),
        (["--set", "algo.bogus=1"], "unknown config key algo.bogus"),
        (["--set", "run.t_max=-5"], "t_max must be >= 1"),
    ],
)
def test_bad_input_exits_2_naming_the_problem(tmp_path, capsys, argv, message):
    assert main(["train", "--out", str(tmp_path / "x"), *argv]) == 2
    assert message in capsys.readouterr().err


def test_broken_yaml_exits_2_naming_file_and_line(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("run:\n  t_max: 100\n  seed: [1\n")
    assert main(["train", "--config", str(bad), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "bad.yaml" in err and "line" in err


def test_nan_loss_stops_and_keeps_last_good_checkpoint(tmp_path, capsys):
    out = tmp_path / "nan"
    # lr = 1e30 makes the first Adam step blow the weights up, so a later loss overflows.
    code = main(
        ["train", "--algo", "vdn", "--env", "matrix/two_step", "--t-max", "400", "--out", str(out),
         "--set", "algo.lr=1e30", "--set", "run.save_interval=2"]
    )  # fmt: skip
    assert code == 3
    assert "loss is not finite" in capsys.readouterr().err
    assert not (out / "summary.json").exists()
    state = torch.load(out / "checkpoint" / "learner.pt", weights_only=False)
    assert state["updates"] >= 1
    for tensor in state["agent"].values():
        assert torch.isfinite(tensor).all()
