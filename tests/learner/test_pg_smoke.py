"""One fast end-to-end smoke test per PG algorithm through the real local trainer (its data
plan, buffer tables and softmax acting), and `credit train` checkpoint/resume for EM-CAC."""

import json

import numpy as np
import pytest
import torch

from cluster.cli import main
from cluster.config.train import load_train_config
from cluster.launch.local import LocalTrainer
from cluster.process import configure
from learner.registry import ALGOS

PG_ALGOS = sorted(name for name, spec in ALGOS.items() if spec.family == "pg")
# Small tables keep skirmish fast; the data flow (cycling + replay) is the shipped one.
SMALL = ["cycling.capacity=8", "replay.batch_size=4", "run.test_episodes=2"]


@pytest.mark.parametrize("env", ["matrix/four_game", "skirmish/3m"])
@pytest.mark.parametrize("name", PG_ALGOS)
def test_trainer_smoke(name, env):
    t_max = 120 if env == "matrix/four_game" else 600
    cfg = load_train_config(name, env, [], [f"run.t_max={t_max}", *SMALL])
    configure(cfg.run)
    trainer = LocalTrainer(cfg, n_ensemble=2)
    records = []
    trainer.train(on_eval=records.extend)
    spec = ALGOS[name]
    assert trainer.core.learner.policy_kind == "softmax" and trainer.core.learner.updates > 0
    m = trainer.core.means.last
    assert all(np.isfinite(v) for v in m.values())
    assert ("kl_masked_fraction" in m) == (name in ("mcac", "emcac"))
    assert ("loss_critic_extra" in m) == spec.extended
    assert records and {r.member for r in records} == {0, 1}
    if env == "skirmish/3m":
        assert all(r.test_won_mean is not None for r in records)


def test_emcac_normalises_advantages_by_default_to_unit_scale():
    cfg = load_train_config("emcac", "skirmish/3m", [], ["run.t_max=600", *SMALL])
    configure(cfg.run)
    trainer = LocalTrainer(cfg, 2)
    trainer.train()
    m = trainer.core.means.last
    assert trainer.core.learner.updates > 0 and all(np.isfinite(v) for v in m.values())
    assert 0.1 < m["advantage_abs_mean"] < 3.0  # unit spread (the mean is not shifted)


def test_metric_means_average_every_update_since_the_last_take():
    cfg = load_train_config("emcac", "matrix/four_game", [], ["run.t_max=200", *SMALL])
    configure(cfg.run)
    trainer = LocalTrainer(cfg, n_ensemble=2)
    seen, step = [], trainer.core.learner.step
    trainer.core.learner.step = lambda *a: seen.append(step(*a)) or seen[-1]
    trainer.train()
    assert len(seen) > 2
    means = trainer.core.take_metric_means()
    for key in ("entropy", "kl_masked_fraction", "loss_critic"):
        assert means[key] == pytest.approx(np.mean([m[key] for m in seen]))
    assert trainer.core.means.last == seen[-1]
    assert trainer.core.take_metric_means() == {}  # reset by the take


def test_train_cli_checkpoint_and_resume_keep_the_target_policy(tmp_path):
    out = tmp_path / "run"
    base = ["train", "--algo", "emcac", "--env", "matrix/four_game", "--out", str(out)]
    assert main([*base, "--t-max", "200", "--set", "cycling.capacity=8"]) == 0
    state = torch.load(out / "checkpoint" / "learner.pt", weights_only=False)
    assert set(state) >= {
        "agent",
        "critic",
        "target_critic",
        "target_policy",
        "agent_optimiser",
        "critic_optimiser",
        "updates",
    }
    first = json.loads((out / "summary.json").read_text())
    assert main(["train", "--resume", str(out), "--t-max", "320"]) == 0
    second = json.loads((out / "summary.json").read_text())
    assert second["t_env"] >= 320 and second["updates"] > first["updates"]
    after = torch.load(out / "checkpoint" / "learner.pt", weights_only=False)
    moved = [
        not torch.equal(after["target_policy"][k], state["target_policy"][k])
        for k in state["target_policy"]
    ]
    assert any(moved)
    steps = (
        after["agent_optimiser"]["state"][0]["step"] - state["agent_optimiser"]["state"][0]["step"]
    )
    assert int(steps) == second["updates"] - first["updates"]
