"""The CAC family's pure functions against hand-computed values, and learner properties."""

import math

import numpy as np
import pytest
import torch

from actors.envs import make_vec_env
from actors.policy import ExplorationConfig
from actors.rollout import RolloutWorker
from buffer_service.episode import EpisodeBatch
from learner.batch import TensorBatch, agent_inputs
from learner.networks import AgentNet, unroll
from learner.pg import (
    CACConfig,
    CACLearner,
    actor_critic_advantages,
    masked_log_policy,
    policy_entropy,
    policy_gradient_loss,
)
from learner.registry import ALGOS

G = 0.9
PG_ALGOS = sorted(name for name, spec in ALGOS.items() if spec.family == "pg")


@pytest.mark.parametrize(
    "reward, terminated, mask, target_values, values, lam, returns, advantages",
    [
        # Terminal episode, λ = 0.5: G2 = 2; G1 = 0 + .9 (.5 * 2 + .5 * 2) = 1.8;
        # G0 = 1 + .9 (.5 * 1 + .5 * 1.8) = 2.26; A = G - V.
        (
            [1.0, 0.0, 2.0],
            [0.0, 0.0, 1.0],
            [1.0, 1.0, 1.0],
            [0.5, 1.0, 2.0, 9.0],
            [0.4, 0.8, 1.5],
            0.5,
            [2.26, 1.8, 2.0],
            [1.86, 1.0, 0.5],
        ),
        # Cut by the time limit after 2 steps, then padding: G1 = 1 + .9 * 4 = 4.6;
        # G0 = 1 + .9 (.5 * 0 + .5 * 4.6) = 3.07; padding has G = A = 0.
        (
            [1.0, 1.0, 0.0],
            [0.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.0, 0.0, 4.0, 99.0],
            [0.5, 1.0, 7.0],
            0.5,
            [3.07, 4.6, 0.0],
            [2.57, 3.6, 0.0],
        ),
        # λ = 1 is the Monte-Carlo return; λ = 0 the one-step TD target.
        (
            [1.0, 1.0],
            [0.0, 1.0],
            [1.0, 1.0],
            [0.0, 5.0, 9.0],
            [0.0, 0.0],
            1.0,
            [1.9, 1.0],
            [1.9, 1.0],
        ),
        (
            [1.0, 1.0],
            [0.0, 1.0],
            [1.0, 1.0],
            [0.0, 5.0, 9.0],
            [2.0, 0.0],
            0.0,
            [5.5, 1.0],
            [3.5, 1.0],
        ),
    ],
)
def test_td_lambda_returns_and_advantages(
    reward, terminated, mask, target_values, values, lam, returns, advantages
):
    t = [torch.tensor([x]) for x in (reward, terminated, mask, target_values, values)]
    g, a = actor_critic_advantages(*t, gamma=G, lam=lam)
    torch.testing.assert_close(g[0], torch.tensor(returns))
    torch.testing.assert_close(a[0], torch.tensor(advantages))


@pytest.mark.parametrize(
    "logits, avail, probs, entropy",
    [
        ([0.0, 0.0, 0.0], [True, True, False], [0.5, 0.5, 0.0], math.log(2)),
        ([0.0, math.log(3.0), 5.0], [True, True, False], [0.25, 0.75, 0.0], None),
        ([9.0, 1.0, 2.0], [False, False, True], [0.0, 0.0, 1.0], 0.0),
        ([1.0, 2.0, 3.0], [False, False, False], None, None),  # padding: finite, caller masks
    ],
)
def test_masked_policy_and_entropy(logits, avail, probs, entropy):
    av = torch.tensor(avail)
    logp = masked_log_policy(torch.tensor(logits), av)
    assert torch.isfinite(logp).all()
    if probs is not None:
        torch.testing.assert_close(logp.exp(), torch.tensor(probs))
    h = policy_entropy(logp, av)
    if entropy is None and probs is not None:
        entropy = -(0.25 * math.log(0.25) + 0.75 * math.log(0.75))
    if entropy is not None:
        assert float(h) == pytest.approx(entropy, abs=1e-6)


@pytest.mark.parametrize(
    "mask, beta, expected",
    [
        # -mean(ln .5 * 2 + .1 ln 2, ln .25 * -1 + .1 * 1)
        ([1.0, 1.0], 0.1, -0.5 * (2 * math.log(0.5) + 0.1 * math.log(2) - math.log(0.25) + 0.1)),
        ([1.0, 0.0], 0.1, -(2 * math.log(0.5) + 0.1 * math.log(2))),
        ([1.0, 1.0], 0.0, -0.5 * (2 * math.log(0.5) - math.log(0.25))),
    ],
)
def test_policy_gradient_loss(mask, beta, expected):
    logp = torch.tensor([[math.log(0.5), math.log(0.25)]])
    adv = torch.tensor([[2.0, -1.0]])
    ent = torch.tensor([[math.log(2), 1.0]])
    loss = policy_gradient_loss(logp, adv, ent, torch.tensor([mask]), beta)
    assert loss.shape == (1,)
    assert float(loss) == pytest.approx(expected, abs=1e-6)


def test_policy_gradient_raises_the_probability_of_advantageous_actions():
    logits = torch.zeros(1, 1, 1, 1, 3, requires_grad=True)
    logp = masked_log_policy(logits, torch.ones(1, 1, 1, 1, 3, dtype=torch.bool))
    taken = logp[..., 1]
    loss = policy_gradient_loss(taken, torch.ones_like(taken), taken * 0, torch.ones_like(taken), 0)
    loss.sum().backward()
    assert logits.grad[..., 1] < 0 < logits.grad[..., 0]  # gradient descent raises action 1


def _episodes(env_id: str, n: int, seed: int = 0):
    venv = make_vec_env(env_id, n, seed=seed)
    info = venv.info
    net = AgentNet(1, info.obs_shape + info.n_actions + info.n_agents, info.n_actions)
    worker = RolloutWorker(venv, net, "softmax", ExplorationConfig(), seed=seed)
    return info, EpisodeBatch.from_episodes(worker.collect(n, t_env=0))


@pytest.mark.parametrize("name", PG_ALGOS)
def test_agent_policy_ignores_other_agents_inputs(name):
    """Decentralised actors: perturbing agent 1's observations leaves agent 0's policy alone."""
    info, batch = _episodes("skirmish/3m", 2)
    spec = ALGOS[name]
    learner = spec.build(spec.config_cls(), info.schema(), 1, "cpu")
    tb = TensorBatch.from_episodes(batch)
    obs2 = tb.obs.clone()
    obs2[..., 1, :] += torch.randn_like(obs2[..., 1, :])
    outs = [
        unroll(learner.agent, agent_inputs(o, tb.actions, info.n_actions)) for o in (tb.obs, obs2)
    ]
    torch.testing.assert_close(outs[0][..., 0, :], outs[1][..., 0, :])
    torch.testing.assert_close(outs[0][..., 2, :], outs[1][..., 2, :])
    assert not torch.allclose(outs[0][..., 1, :], outs[1][..., 1, :])


@pytest.mark.parametrize(
    "critic_input, sees_obs, sees_state",
    [("obs", True, False), ("state", False, True), ("obs_state", True, True)],
)
def test_central_critic_inputs(critic_input, sees_obs, sees_state):
    """The CAC critic is centralised: it sees every agent's observation (and the state if
    asked), not just one agent's."""
    info, batch = _episodes("skirmish/3m", 2)
    learner = CACLearner(CACConfig(critic_input=critic_input), info.schema())
    tb = TensorBatch.from_episodes(batch)
    base = learner.values(tb, learner.critic)
    obs2 = tb.obs.clone()
    obs2[..., 2, :] += 1.0
    state2 = tb.state + 1.0
    v_obs = learner.values(TensorBatch(**{**tb.__dict__, "obs": obs2}), learner.critic)
    v_state = learner.values(TensorBatch(**{**tb.__dict__, "state": state2}), learner.critic)
    assert (not torch.allclose(base, v_obs)) == sees_obs
    assert (not torch.allclose(base, v_state)) == sees_state


@pytest.mark.parametrize("name", ["emcac", "coma"])
def test_seed_batched_update_equals_separate_updates(name):
    """Member k of an E=2 learner follows the update an E=1 learner with member k's weights
    would follow on member k's batch: per-member losses are summed, never averaged."""
    info, ba = _episodes("matrix/four_game", 4, seed=0)
    _, bb = _episodes("matrix/four_game", 4, seed=1)
    spec = ALGOS[name]
    torch.manual_seed(0)
    pair = spec.build(spec.config_cls(), info.schema(), 2, "cpu")
    init = {k: v.clone() for k, v in pair.state_dict()["agent"].items()}
    critic_init = {k: v.clone() for k, v in pair.state_dict()["critic"].items()}
    extra = EpisodeBatch.stack([bb, ba])
    pair.step(EpisodeBatch.stack([ba, bb]), extra)
    for member, batch, xb in ((0, ba, bb), (1, bb, ba)):
        single = spec.build(spec.config_cls(), info.schema(), 1, "cpu")
        single.agent.load_state_dict({k: v[member : member + 1] for k, v in init.items()})
        single.critic.load_state_dict({k: v[member : member + 1] for k, v in critic_init.items()})
        single.target_critic.module.load_state_dict(single.critic.state_dict())
        if getattr(single, "target_policy", None) is not None:
            single.target_policy.load_state_dict(single.agent.state_dict())
        single.step(batch, xb)
        for mod in ("agent", "critic"):
            for k, v in getattr(single, mod).state_dict().items():
                got = getattr(pair, mod).state_dict()[k][member]
                torch.testing.assert_close(v[0], got, atol=1e-5, rtol=1e-4)


def test_extended_variants_run_a_second_critic_pass_only_with_an_extra_batch():
    info, batch = _episodes("matrix/four_game", 4)
    ecac = ALGOS["ecac"].build(CACConfig(), info.schema(), 1, "cpu")
    assert "loss_critic_extra" in ecac.step(batch, batch)
    assert "loss_critic_extra" not in ecac.step(batch)
    cac = ALGOS["cac"].build(CACConfig(), info.schema(), 1, "cpu")
    assert "loss_critic_extra" not in cac.step(batch, batch)  # on-policy: extra is ignored
    # Adam counted two critic steps for the extended update, one for the plain one.
    steps = ecac.critic_updater.optimiser.state_dict()["state"][0]["step"]
    assert int(steps) == 3


@pytest.mark.parametrize(
    "field_name, value, message",
    [
        ("td_lambda", 1.5, "td_lambda must be in [0, 1]"),
        ("kl_threshold", 0.0, "kl_threshold must be > 0"),
        ("polyak_tau", 0.0, "polyak_tau must be in (0, 1]"),
        ("entropy_coef", -0.1, "entropy_coef must be >= 0"),
        ("critic_lr", -1.0, "critic_lr must be > 0"),
        ("critic_hidden", (), "critic_hidden needs at least one positive width"),
    ],
)
def test_config_validation_names_the_field(field_name, value, message):
    with pytest.raises(ValueError) as e:
        CACConfig(**{field_name: value}).validate()
    assert message in str(e.value)


def test_metrics_are_finite_and_name_the_mask():
    info, batch = _episodes("skirmish/3m", 4)
    for name, has_kl in (("cac", False), ("mcac", True)):
        learner = ALGOS[name].build(CACConfig(), info.schema(), 1, "cpu")
        m = learner.step(batch)
        assert ("kl_masked_fraction" in m) == has_kl
        assert all(np.isfinite(v) for v in m.values())


@pytest.mark.parametrize("name", PG_ALGOS)
def test_padding_is_ignored_with_ragged_episodes_and_the_extra_batch(name):
    """Ragged skirmish episodes padded further (main and extra batch) give the same update."""
    info, batch = _episodes("skirmish/3m", 3)
    _, extra = _episodes("skirmish/3m", 3, seed=1)
    spec = ALGOS[name]
    results = []
    for pad in (0, 4):
        torch.manual_seed(1)
        learner = spec.build(spec.config_cls(), info.schema(), 1, "cpu")
        main_b = batch.pad_to(batch.max_t + pad) if pad else batch
        extra_b = extra.pad_to(extra.max_t + pad) if pad else extra
        metrics = learner.step(main_b, extra_b)
        results.append((metrics, learner.state_dict()))
    for k, v in results[0][0].items():
        assert results[1][0][k] == pytest.approx(v, rel=1e-5, abs=1e-6), k
    for mod in ("agent", "critic"):
        for k, v in results[0][1][mod].items():
            torch.testing.assert_close(v, results[1][1][mod][k], atol=1e-6, rtol=1e-5)


def test_normalised_advantages_have_unit_spread_on_real_entries_only():
    from learner.pg import normalised_advantages

    adv = torch.tensor([[1.0, 3.0, 100.0], [2.0, -2.0, 0.0]])
    mask = torch.tensor([[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]])
    out = normalised_advantages(adv, mask)
    # member 0: real entries 1, 3 -> std 1 -> unchanged; the padding entry becomes 0
    assert torch.allclose(out[0], torch.tensor([1.0, 3.0, 0.0]))
    # member 1: entries 2, -2, 0 -> mean 0, std sqrt(8/3); signs kept, no mean shift
    assert torch.allclose(out[1], torch.tensor([2.0, -2.0, 0.0]) / (8.0 / 3.0) ** 0.5)


@pytest.mark.parametrize("algo", ["cac", "ecac", "mcac", "emcac"])
def test_advantage_norm_is_on_by_default_and_can_be_turned_off(algo):
    from cluster.config.train import load_train_config

    assert CACConfig().advantage_norm is True
    assert load_train_config(algo, "skirmish/3m").algo.advantage_norm is True
    cfg = load_train_config(algo, "skirmish/3m", [], ["algo.advantage_norm=false"])
    assert cfg.algo.advantage_norm is False
