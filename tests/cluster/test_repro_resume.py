"""`credit repro` pairs that survive interruption (cluster.repro.resume): a pair stopped and
resumed writes the evaluation log of a pair that ran through, a killed one loses less than
--checkpoint-every env steps, finished pairs are skipped, other settings are refused."""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from cluster.cli import main
from cluster.repro import curves
from cluster.repro.pairs import Collector, Pair, Reporter
from cluster.repro.resume import JOURNAL, RESUME_FOLDER, ResumeConfig, _checkpoint_journal
from tests.cluster.polling import wait_for

ROOT = Path(__file__).resolve().parents[2]
MATRIX = ["run.t_max=120", "run.test_interval=20", "replay.batch_size=8"]
SKIRMISH = ["run.t_max=800", "run.test_interval=100", "run.test_episodes=2"]
SKIRMISH += ["replay.batch_size=4"]


class DiedError(Exception):
    """Stands for the process dying: raised from inside the training loop."""


class _Sink:
    """Events straight to a real Collector (as with --workers 1); raises DiedError at the
    `stop_at`-th evaluation, before the checkpoint the loop would write after it."""

    def __init__(self, collector: Collector, stop_at: int | None = None):
        self.collector, self.stop_at, self.evaluations = collector, stop_at, 0
        self.kinds: list[str] = []

    def put(self, event) -> None:
        self.kinds.append(event.kind)
        self.collector.handle(event)
        if event.kind == "evaluated":
            self.evaluations += 1
            if self.evaluations == self.stop_at:
                raise DiedError


def _run(tmp: Path, pair: Pair, overrides: list[str], every: int, commit: str, stop_at=None):
    """One attempt at `pair` (2 seeds) reporting into tmp/evals; returns (output, sink)."""
    resume = ResumeConfig(str(tmp), every, commit, {"seeds": 2, "overrides": overrides})
    (tmp / "evals").mkdir(parents=True, exist_ok=True)
    sink = _Sink(Collector([pair], tmp / "evals"), stop_at)
    report = Reporter(sink, pair)
    report.start()
    out = curves.run_pair(pair.algo, pair.env, 2, overrides, False, resume, report=report)
    return out, sink


def _log(tmp: Path, pair: Pair) -> list[dict]:
    return [json.loads(x) for x in (tmp / "evals" / f"{pair.key}.jsonl").read_text().splitlines()]


def _without(rows: list[dict], *keys: str) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in keys} for r in rows]


def _stopped_and_resumed_is_the_straight_run(tmp_path, pair, overrides, every, stop_at):
    straight, _ = _run(tmp_path / "straight", pair, overrides, every, "c1")
    with pytest.raises(DiedError):
        _run(tmp_path / "stopped", pair, overrides, every, "c1", stop_at)
    saved = json.loads((tmp_path / "stopped" / RESUME_FOLDER / pair.key / JOURNAL).read_text())
    assert 0 < saved["t_env"] < _log(tmp_path / "stopped", pair)[-1]["t_env"]
    resumed, sink = _run(tmp_path / "stopped", pair, overrides, every, "c2")
    assert sink.kinds[:2] == ["started", "resumed"]
    a, b = _log(tmp_path / "straight", pair), _log(tmp_path / "stopped", pair)
    assert len(a) > stop_at and _without(a, "wall_s", "commit") == _without(b, "wall_s", "commit")
    # rows up to the checkpoint were trained at c1, the rest at c2; the curve names both
    assert {r["commit"] for r in b if r["t_env"] <= saved["t_env"]} == {"c1"}
    assert {r["commit"] for r in b if r["t_env"] > saved["t_env"]} == {"c2"}
    assert resumed.curve.commits == ["c1", "c2"] and straight.curve.commits == ["c1"]
    assert resumed.curve.learner == straight.curve.learner  # the losses, to the last bit
    # a finished pair leaves no checkpoint behind
    assert not (tmp_path / "stopped" / RESUME_FOLDER).exists()


@pytest.mark.parametrize("algo", ["qmix", "rdn"])
def test_a_stopped_and_resumed_matrix_pair_writes_the_straight_runs_log(tmp_path, algo):
    pair = Pair(algo, "matrix/two_step")
    _stopped_and_resumed_is_the_straight_run(tmp_path, pair, MATRIX, 40, stop_at=4)


@pytest.mark.slow  # about 40 s on the 2-core machine
def test_a_stopped_and_resumed_skirmish_pair_writes_the_straight_runs_log(tmp_path):
    """skirmish draws its start positions from the envs' own generators: they are in the
    checkpoint too."""
    pair = Pair("qmix", "skirmish/3m")
    _stopped_and_resumed_is_the_straight_run(tmp_path, pair, SKIRMISH, 200, stop_at=4)


def test_finished_pairs_are_skipped_and_other_settings_refused(tmp_path, capsys, caplog):
    args = ["repro", "matrix", "--algos", "vdn", "--games", "matrix/two_step", "--seeds", "2"]
    args += ["--t-max", "200", "--workers", "1", "--checkpoint-every", "50"]
    args += ["--out", str(tmp_path)]
    caplog.set_level(logging.INFO)
    assert main(args) == 0
    first = (tmp_path / "summary.json").read_text()
    log = (tmp_path / "evals" / "matrix-two_step__vdn.jsonl").read_text()
    assert (tmp_path / "pairs" / "matrix-two_step__vdn.json").exists()
    assert not (tmp_path / RESUME_FOLDER).exists()
    caplog.clear()
    assert main(args) == 0
    assert "pair vdn@matrix/two_step finished in an earlier run; not run again" in caplog.text
    assert (tmp_path / "evals" / "matrix-two_step__vdn.jsonl").read_text() == log
    again = json.loads((tmp_path / "summary.json").read_text())
    assert again == json.loads(first) and again["vdn"]["two_step"]["commits"]
    capsys.readouterr()
    assert main([*args[:-4], "--t-max", "300", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "made with other settings" in err and "run.t_max=200" in err
    assert main([*args, "--checkpoint-every", "-1"]) == 2
    assert "--checkpoint-every must be >= 0" in capsys.readouterr().err


@pytest.mark.slow  # about 60 s at load 5: three `credit repro` processes
def test_a_pair_killed_with_kill_9_loses_less_than_checkpoint_every_steps(tmp_path):
    every = 100
    args = [sys.executable, "-m", "cluster.cli", "repro", "matrix", "--algos", "qmix"]
    args += ["--games", "matrix/two_step", "--seeds", "2", "--t-max", "1000", "--workers", "1"]
    args += ["--checkpoint-every", str(every), "--set", "run.test_interval=20"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    straight = subprocess.run(
        [*args, "--out", str(tmp_path / "straight")], env=env, capture_output=True, timeout=600
    )
    assert straight.returncode == 0, straight.stderr[-3000:]
    out = tmp_path / "killed"
    evals = out / "evals" / "matrix-two_step__qmix.jsonl"
    journal = out / RESUME_FOLDER / "matrix-two_step__qmix" / JOURNAL
    proc = subprocess.Popen([*args, "--out", str(out)], env=env, stderr=subprocess.DEVNULL)
    try:

        def progressed() -> int | None:  # past its second checkpoint
            if not journal.exists() or json.loads(journal.read_text())["t_env"] < 2 * every:
                return None
            return len(evals.read_text().splitlines())

        wait_for(progressed, timeout_s=300, what="the second checkpoint", proc=proc)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    # How far it got: at least its newest whole checkpoint and its last logged evaluation
    # (the driver writes the log from the pair's events, so the log may lag the checkpoint).
    kept = json.loads(_checkpoint_journal(journal.parent).read_text())["t_env"]
    reached = max(kept, json.loads(evals.read_text().splitlines()[-1])["t_env"])
    again = subprocess.run(
        [*args, "--out", str(out)], env=env, capture_output=True, text=True, timeout=600
    )
    assert again.returncode == 0, again.stderr[-3000:]
    resumed = re.search(r"resumed from its checkpoint at t_env (\d+)", again.stderr)
    assert resumed, again.stderr[-3000:]
    assert int(resumed.group(1)) == kept >= 2 * every  # its newest whole checkpoint
    assert reached - kept < every
    assert re.search(r"checkpoint at t_env \d+: [\d.]+ MB in ", again.stderr)  # its disk
    a, b = (
        _without(
            [json.loads(x) for x in (d / "evals" / evals.name).read_text().splitlines()],
            "wall_s",
            "commit",
        )
        for d in (tmp_path / "straight", out)
    )
    assert a == b and a[-1]["t_env"] >= 1000


def test_a_pair_trained_twice_at_once_into_one_folder_is_refused(tmp_path):
    from cluster.config.train import load_train_config
    from cluster.errors import UsageError
    from cluster.launch.local import LocalTrainer
    from cluster.repro.resume import PairJournal

    pair = Pair("vdn", "matrix/two_step")
    resume = ResumeConfig(str(tmp_path), 40, "c1", {"seeds": 1, "overrides": []})
    cfg = load_train_config("vdn", "matrix/two_step", [], ["run.t_max=40"])
    busy = pytest.raises(UsageError, match="another process is training into")
    with PairJournal(resume, pair) as first:
        first.attach(LocalTrainer(cfg))
        with busy, PairJournal(resume, pair) as second:
            second.attach(LocalTrainer(cfg))
    with PairJournal(resume, pair) as third:  # the first let go of it
        third.attach(LocalTrainer(cfg))
