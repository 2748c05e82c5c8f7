"""run.loggers: `credit train` writes TensorBoard event files that TensorBoard's own reader
loads, with metrics.jsonl's scalars and the learner's losses; W&B in its offline mode; the
default writes metrics.jsonl alone. Cluster mode: test_cluster_mode.py checks the same files
(`assert_event_files_match_metrics`)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from cluster.cli import main
from cluster.metrics import run_loggers

TRAIN = ["train", "--algo", "qmix", "--env", "matrix/two_step", "--t-max", "120"]
TRAIN += ["--set", "run.test_interval=40", "--set", "replay.batch_size=8"]


def assert_event_files_match_metrics(out: Path) -> dict:
    """Every metrics.jsonl field at every evaluation is a TensorBoard scalar at step t_env
    (read with tensorboard's EventAccumulator), and learner/<loss> scalars are there;
    returns {tag: [(step, value)]}."""
    pytest.importorskip("tensorboard", reason="tensorboard not installed (credit[tensorboard])")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    files = list((out / "tensorboard").glob("events.out.tfevents.*"))
    assert files, f"no event file in {out / 'tensorboard'}"
    acc = EventAccumulator(str(out / "tensorboard"))
    acc.Reload()
    scalars = {t: [(e.step, e.value) for e in acc.Scalars(t)] for t in acc.Tags()["scalars"]}
    rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert rows
    for key in rows[0]:
        if key == "t_env":
            continue
        want = [(r["t_env"], r[key]) for r in rows]
        got = scalars[key]
        assert [s for s, _ in got] == [s for s, _ in want], key
        assert [v for _, v in got] == pytest.approx([v for _, v in want], rel=1e-6), key
    assert any(t.startswith("learner/loss") for t in scalars), sorted(scalars)
    return scalars


def test_tensorboard_event_files_hold_the_metrics_and_losses(tmp_path):
    out = tmp_path / "run"
    argv = [*TRAIN, "--out", str(out), "--set", "run.loggers=[jsonl,tensorboard]"]
    assert main(argv) == 0
    scalars = assert_event_files_match_metrics(out)
    assert "learner/loss_td" in scalars and "test_return_mean" in scalars
    # the losses are means since the previous evaluation: none before the first update
    assert scalars["learner/loss_td"][0][0] > 0
    config = (out / "config.yaml").read_text()
    assert "- tensorboard" in config


def test_default_writes_metrics_jsonl_only(tmp_path):
    out = tmp_path / "run"
    assert main([*TRAIN, "--out", str(out)]) == 0
    assert (out / "metrics.jsonl").read_text().strip()
    assert not (out / "tensorboard").exists() and not (out / "wandb").exists()


@pytest.mark.parametrize(
    "loggers, message",
    [
        ("[tensorboard]", "loggers must name jsonl"),
        ("[jsonl,jsonl]", "each logger once"),
        ("[jsonl,csv]", "'csv' is not one of"),
    ],
)
def test_bad_loggers_exit_2(tmp_path, capsys, loggers, message):
    argv = [*TRAIN, "--out", str(tmp_path / "run"), "--set", f"run.loggers={loggers}"]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_wandb_offline_run(tmp_path, monkeypatch):
    wandb = pytest.importorskip("wandb", reason="wandb not installed (pip install 'credit[wandb]')")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    out = tmp_path / "run"
    assert main([*TRAIN, "--out", str(out), "--set", "run.loggers=[jsonl,wandb]"]) == 0
    runs = list((out / "wandb").glob("offline-run-*"))
    assert len(runs) == 1 and list(runs[0].glob("*.wandb")), os.listdir(out / "wandb")
    assert wandb.run is None  # finished


def test_missing_package_is_named(tmp_path, capsys, monkeypatch):
    # wandb is installed with the dev extra, so the logger is pointed at a package that is not
    monkeypatch.setitem(run_loggers._PACKAGES, "wandb", "credit_test_no_such_package")
    argv = [*TRAIN, "--out", str(tmp_path / "run"), "--set", "run.loggers=[jsonl,wandb]"]
    assert main(argv) == 2
    assert "pip install 'credit[wandb]'" in capsys.readouterr().err
