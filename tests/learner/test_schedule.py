"""The value family's data schedule and its options: feed-forward agents, episode-counted
target refreshes, reward normalisation, optimisers, and the replay ratio in the local loop."""

import pytest
import torch

from cluster.config.schema import ConfigError
from cluster.config.train import load_train_config
from cluster.launch.local import LocalTrainer
from cluster.process import configure
from learner.common import EpisodeClock, RewardNorm, Updater
from learner.networks import AgentNet, unroll


def test_feed_forward_agent_has_no_memory_and_unrolls_in_one_call():
    torch.manual_seed(0)
    net = AgentNet(2, input_dim=5, n_actions=3, recurrent=False)
    x = torch.randn(2, 4, 6, 3, 5)  # [E, B, T, N, D]
    out = unroll(net, x)
    x2 = x.clone()
    x2[:, :, 0] += 1.0  # change only the first step
    out2 = unroll(net, x2)
    torch.testing.assert_close(out[:, :, 1:], out2[:, :, 1:])  # later steps do not see it
    assert not torch.allclose(out[:, :, 0], out2[:, :, 0])
    # one step at a time (as the actors call it) gives the same as the batched unroll
    h = net.init_hidden(2, 4 * 3)
    step, _ = net(x[:, :, 2].reshape(2, 12, 5), h)
    torch.testing.assert_close(step.view(2, 4, 3, 3), out[:, :, 2])


def test_episode_clock_fires_once_per_crossed_multiple():
    clock = EpisodeClock(200)
    fired = [n for n in range(0, 1001, 8) if clock.due(n)]
    assert fired == [200, 400, 600, 800, 1000]
    clock = EpisodeClock(200)
    assert clock.due(450) and not clock.due(451) and clock.due(600)


def test_reward_norm_by_hand():
    r = torch.tensor([[[1.0, 3.0, 0.0], [5.0, 7.0, 9.0]]])  # [E=1, B=2, T=3]
    mask = torch.tensor([[[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]]])  # the 0.0 is padding
    real = torch.tensor([1.0, 3.0, 5.0, 7.0, 9.0])
    mean, std = real.mean(), real.std(unbiased=False)
    scaled = RewardNorm("scale", 1)(r, mask)
    torch.testing.assert_close(scaled, r / std * mask)
    standard = RewardNorm("standardise", 1)(r, mask)
    torch.testing.assert_close(standard, (r - mean) / std * mask)
    assert RewardNorm("none", 1)(r, mask) is r
    # statistics accumulate over batches exactly as over their union
    norm = RewardNorm("scale", 1)
    norm(r[:, :1], mask[:, :1])
    out = norm(r[:, 1:], mask[:, 1:])
    torch.testing.assert_close(out, r[:, 1:] / std)
    with pytest.raises(ValueError, match="reward_norm 'z' is not one of"):
        RewardNorm("z", 1)


def test_rmsprop_updater_and_unknown_optimiser():
    p = torch.nn.Parameter(torch.ones(1, 3))
    up = Updater([p], 0.1, 10.0, "t", optimiser="rmsprop")
    assert isinstance(up.optimiser, torch.optim.RMSprop)
    up.apply((p**2).sum().unsqueeze(0))
    assert torch.all(p < 1.0)
    with pytest.raises(ValueError, match="optimiser 'sgd' is not one of"):
        Updater([p], 0.1, 10.0, "t", optimiser="sgd")


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["algo.target_update_interval=200"], "unknown config key algo.target_update_interval"),
        (["algo.optimiser=sgd"], "algo.optimiser: 'sgd' is not one of"),
        (["algo.reward_norm=minmax"], "algo.reward_norm: 'minmax' is not one of"),
        (["algo.td_lambda=1.5"], "td_lambda must be in [0, 1]"),
        (["replay.updates_per_episode=0"], "updates_per_episode must be > 0"),
    ],
)
def test_schedule_keys_are_checked(overrides, message):
    for algo in ("qmix", "rdn"):
        with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
            load_train_config(algo, "skirmish/3m", overrides=overrides)


def _schedule(algo: str, num_envs: int, upe: float, episodes: int) -> tuple[int, int]:
    """(learner updates, target refreshes) after training `episodes` episodes locally."""
    cfg = load_train_config(
        algo,
        "matrix/two_step",
        overrides=[
            f"run.num_envs={num_envs}",
            f"replay.updates_per_episode={upe}",
            "replay.batch_size=4",
            "algo.target_update_episodes=10",
            f"run.t_max={2 * episodes}",  # two steps per episode
            "run.test_interval=100000",
        ],
    )
    configure(cfg.run)
    trainer = LocalTrainer(cfg)
    learner = trainer.core.learner
    refreshes = 0
    original = learner.sync_targets

    def counting(episodes: int) -> bool:
        nonlocal refreshes
        fired = original(episodes)
        refreshes += fired
        return fired

    learner.sync_targets = counting
    trainer.train()
    assert trainer.core.episodes == episodes
    return learner.updates, refreshes


@pytest.mark.parametrize("algo", ["vdn", "rdn"])
@pytest.mark.parametrize("upe", [1.0, 0.5, 2.0])
def test_updates_and_target_refreshes_per_episode_do_not_depend_on_num_envs(algo, upe):
    """120 episodes: the first 4 fill the batch, then upe updates per episode; a target copy
    every 10 episodes, whatever the number of envs stepped together."""
    results = {n: _schedule(algo, n, upe, 120) for n in (1, 4, 8)}
    updates = {n: u for n, (u, _) in results.items()}
    refreshes = {n: r for n, (_, r) in results.items()}
    expected = upe * (120 - 8)  # 8: the warm-up round of the widest setting, at most
    for n, u in updates.items():
        assert expected <= u <= upe * 120, (n, updates)
    assert max(updates.values()) - min(updates.values()) <= upe * 8, updates
    assert set(refreshes.values()) == {12}, refreshes
