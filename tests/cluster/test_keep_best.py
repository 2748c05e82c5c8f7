"""run.keep_best: the policy of a run's best greedy evaluation, kept in best/ beside
checkpoint/ (what `credit demo` reports alongside the final policy)."""

import json

import pytest
import torch

from cluster.cli import main
from cluster.config.schema import ConfigError
from cluster.config.train import load_train_config
from cluster.core import TrainerCore
from cluster.evaluation import EvalRecord
from cluster.launch.local import LocalTrainer
from cluster.process import configure

SETS = ["run.test_interval=50", "replay.batch_size=4", "run.keep_best=true"]


def _trainer(tmp_path, *sets: str) -> LocalTrainer:
    cfg = load_train_config("vdn", "matrix/two_step", [], [*SETS, *sets])
    configure(cfg.run)
    return LocalTrainer(cfg, checkpoint_dir=tmp_path / "checkpoint")


def _record(t_env: int, won: float | None, ret: float = 0.0) -> EvalRecord:
    return EvalRecord(0, t_env, 0, ret, won, 1.0, 0)


def _saved_agent(folder):
    return torch.load(folder / "learner.pt", weights_only=False)["agent"]


def test_the_best_evaluation_is_kept_and_a_later_tie_replaces_it(tmp_path):
    core = _trainer(tmp_path, "run.t_max=10").core
    best = tmp_path / "best"
    assert core.keep_if_best(_record(100, 0.5))
    first = {k: v.clone() for k, v in core.learner.state_dict()["agent"].items()}
    with torch.no_grad():
        for p in core.learner.agent.parameters():
            p.add_(1.0)
    assert not core.keep_if_best(_record(200, 0.3))  # worse: best/ keeps the first policy
    assert json.loads((best / "best.json").read_text())["t_env"] == 100
    assert all(torch.equal(first[k], v) for k, v in _saved_agent(best).items())
    assert core.keep_if_best(_record(300, 0.5))  # a tie: the later policy
    assert json.loads((best / "best.json").read_text())["test_won_mean"] == 0.5
    assert json.loads((best / "best.json").read_text())["t_env"] == 300
    now = core.learner.state_dict()["agent"]
    assert all(torch.equal(now[k], v) for k, v in _saved_agent(best).items())


def test_without_a_win_rate_the_return_decides(tmp_path):
    core = _trainer(tmp_path, "run.t_max=10").core
    assert core.keep_if_best(_record(50, None, ret=2.0))
    assert not core.keep_if_best(_record(100, None, ret=1.5))
    assert core.keep_if_best(_record(150, None, ret=8.0))
    assert json.loads((tmp_path / "best" / "best.json").read_text())["t_env"] == 150


def test_a_training_run_keeps_the_last_of_its_best_evaluations(tmp_path):
    out = tmp_path / "run"
    argv = ["train", "--algo", "vdn", "--env", "matrix/two_step", "--out", str(out)]
    for item in [*SETS, "run.t_max=600"]:
        argv += ["--set", item]
    assert main(argv) == 0
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    top = max(r["test_return_mean"] for r in rows)
    expected = [r for r in rows if r["test_return_mean"] == top][-1]
    kept = json.loads((out / "best" / "best.json").read_text())
    assert kept["t_env"] == expected["t_env"] and kept["test_return_mean"] == top
    cfg = load_train_config("vdn", "matrix/two_step", [], ["run.t_max=600"])
    core = TrainerCore(cfg, 1)
    core.restore(out / "best")
    assert core.t_env == expected["t_env"]


def test_a_resumed_run_remembers_its_best_score(tmp_path):
    first = _trainer(tmp_path, "run.t_max=150")
    first.train()
    assert first.core.best_score is not None
    first.save(tmp_path / "checkpoint")
    resumed = _trainer(tmp_path, "run.t_max=300")
    resumed.restore(tmp_path / "checkpoint")
    assert resumed.core.best_score == first.core.best_score


@pytest.mark.parametrize("n_ensemble, folder", [(2, True), (1, False)])
def test_keep_best_needs_one_seed_and_a_checkpoint_folder(tmp_path, n_ensemble, folder):
    cfg = load_train_config("vdn", "matrix/two_step", [], [*SETS, "run.t_max=10"])
    with pytest.raises(ConfigError, match=r"run\.keep_best needs a run of one seed"):
        TrainerCore(cfg, n_ensemble, tmp_path / "checkpoint" if folder else None)
