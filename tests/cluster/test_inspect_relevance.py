"""`credit inspect relevance`: per-agent credit of RDN, VDN and QMIX checkpoints, grouped by
unit type and alive/dead, as JSON, PNG and GIF."""

import json

import numpy as np
import pytest
import torch

from cluster.cli import main
from cluster.config.train import load_train_config
from cluster.inspect.relevance import credit, find_checkpoint, load_member, play
from cluster.launch.local import LocalTrainer
from cluster.process import configure

ENV = "skirmish/bane_z1"  # 1 zergling + 4 banelings against 20 + 4: short episodes
SMALL = ["run.test_episodes=1", "run.num_envs=1", "replay.batch_size=2", "algo.agent.hidden=8"]


def _checkpoint(tmp_path, algo: str, seeds: int = 1):
    """An untrained run's checkpoint (random networks) in `credit train`'s layout."""
    cfg = load_train_config(algo, ENV, [], SMALL)
    configure(cfg.run)
    trainer = LocalTrainer(cfg, n_ensemble=seeds)
    run = tmp_path / f"{algo}_run"
    trainer.save(run / "checkpoint")
    return run


@pytest.mark.parametrize(
    "algo",
    [
        "rdn",
        pytest.param("vdn", marks=pytest.mark.slow),
        pytest.param("qmix", marks=pytest.mark.slow),
    ],
)
def test_inspect_writes_grouped_credit_png_and_gif(tmp_path, algo, capsys):
    run = _checkpoint(tmp_path, algo)
    out = tmp_path / "out"
    argv = ["inspect", "relevance", "--run", str(run), "--episodes", "2", "--out", str(out)]
    assert main([*argv, "--max-frames", "5"]) == 0
    got = json.loads((out / "relevance.json").read_text())
    assert (out / "relevance.png").stat().st_size > 0 and (out / "relevance.gif").stat().st_size
    assert got["algo"] == algo and got["env"] == ENV and len(got["per_episode"]) == 2
    assert {a["type"] for a in got["per_agent"]} == {"baneling", "zergling"}
    steps = sum(e["length"] for e in got["per_episode"])
    assert sum(g["agent_steps"] for g in got["groups"].values()) == steps * 5
    assert set(got["groups"]) <= {
        f"{k}/{s}" for k in ("baneling", "zergling") for s in ("alive", "dead")
    }
    for ep in got["per_episode"]:
        c = np.asarray(ep["credit"])
        if algo == "rdn":  # LRP-eps with the residual rule conserves the critic's value
            np.testing.assert_allclose(c.sum(-1), ep["q_total"], atol=1e-3)
        elif algo == "vdn":
            np.testing.assert_allclose(c, ep["utility"], atol=1e-6)
            np.testing.assert_allclose(c.sum(-1), ep["q_total"], atol=1e-4)
        else:  # QMIX: monotonic mixer, credit = gradient x utility
            assert (np.asarray(ep["mixer_grad"]) >= 0).all()
            np.testing.assert_allclose(c, np.multiply(ep["mixer_grad"], ep["utility"]), atol=1e-5)
    assert "groups" in json.loads(capsys.readouterr().out.splitlines()[0])


@pytest.mark.parametrize("algo", ["vdn", "qmix"])
def test_value_family_credit_is_the_utility_or_gradient_times_utility(tmp_path, algo):
    cfg, learner = load_member(find_checkpoint(_checkpoint(tmp_path, algo)), 0)
    episodes, _, _ = play(cfg, learner, 2, seed=1)
    parts = credit(cfg, learner, episodes)
    if algo == "vdn":
        np.testing.assert_array_equal(parts["credit"], parts["utility"])
        np.testing.assert_allclose(parts["q_total"], parts["utility"].sum(-1), atol=1e-5)
    else:
        assert (parts["mixer_grad"] >= 0).all() and parts["mixer_grad"][parts["mask"]].max() > 0
        np.testing.assert_allclose(parts["credit"], parts["mixer_grad"] * parts["utility"])


def test_alive_flags_are_the_units_that_observe_something(tmp_path):
    run = _checkpoint(tmp_path, "vdn")
    cfg, learner = load_member(find_checkpoint(run), 0)
    episodes, won, rec = play(cfg, learner, 2, seed=3)
    assert len(won) == 2
    for k, ep in enumerate(episodes):
        for t in range(int(ep.filled.sum())):
            alive = np.asarray(rec.frames[k][t]["alive"][: ep.obs.shape[1]])
            np.testing.assert_array_equal(alive, np.abs(ep.obs[t]).sum(-1) > 0)


def test_a_member_of_a_seed_batched_checkpoint_is_that_seed(tmp_path):
    run = _checkpoint(tmp_path, "rdn", seeds=2)
    ckpt = find_checkpoint(run)
    cfg, first = load_member(ckpt, 0)
    _, second = load_member(ckpt, 1)
    state = torch.load(ckpt / "learner.pt", weights_only=False)
    for name, value in second.critic.state_dict().items():  # every tensor, member 1's slice
        torch.testing.assert_close(value[0], state["critic"][name][1])
    episodes, _, _ = play(cfg, first, 1, seed=0)
    assert not np.allclose(
        credit(cfg, first, episodes)["credit"], credit(cfg, second, episodes)["credit"]
    )


def test_bad_runs_exit_2(tmp_path, capsys):
    assert main(["inspect", "relevance", "--run", str(tmp_path)]) == 2
    assert "no checkpoint" in capsys.readouterr().err
    run = _checkpoint(tmp_path, "vdn")
    assert main(["inspect", "relevance", "--run", str(run), "--member", "3"]) == 2
    assert "--member must be in 0..0" in capsys.readouterr().err
