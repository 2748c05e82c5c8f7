"""EM-CAC's KL mask and Polyak target policy: hand-computed values and learner behaviour."""

import math

import pytest
import torch

from actors.envs import make_vec_env
from actors.policy import ExplorationConfig
from actors.rollout import RolloutWorker
from buffer_service.episode import EpisodeBatch
from learner.kl_mask import (
    categorical_kl,
    joint_kl,
    kl_keep_mask,
    masked_advantages,
    masked_fraction,
    polyak_update_,
)
from learner.networks import AgentNet, EnsembleLinear
from learner.pg import CACConfig, CACLearner


def _log(p):
    return torch.tensor(p).log()


@pytest.mark.parametrize(
    "p, q, avail, expected",
    [
        ([0.5, 0.5], [0.5, 0.5], [True, True], 0.0),
        ([0.5, 0.5], [0.25, 0.75], [True, True], 0.5 * math.log(2) + 0.5 * math.log(2 / 3)),
        ([0.25, 0.75], [0.5, 0.5], [True, True], 0.25 * math.log(0.5) + 0.75 * math.log(1.5)),
        ([0.9, 0.1, 0.0], [0.1, 0.9, 0.0], [True, True, False], 0.8 * math.log(9)),
    ],
)
def test_categorical_kl_by_hand(p, q, avail, expected):
    """KL(p || q) = Σ p log(p / q): the current policy p first (the seed's KL(θ^π || θ̃^π))."""
    kl = categorical_kl(_log(p), _log(q), torch.tensor(avail))
    assert float(kl) == pytest.approx(expected, abs=1e-6)


def test_identical_policies_mask_nothing():
    logp = torch.log_softmax(torch.randn(2, 3, 5, 4, 6), -1)
    avail = torch.ones(2, 3, 5, 4, 6, dtype=torch.bool)
    kl = categorical_kl(logp, logp, avail)
    keep = kl_keep_mask(kl, threshold=1e-6)
    assert torch.equal(keep, torch.ones_like(keep))
    assert masked_fraction(keep, torch.ones_like(keep)).tolist() == [0.0, 0.0]


def test_far_policy_masks_exactly_the_divergent_timesteps():
    """Target equal to the current policy except at (t=1, agent 0) and (t=3, agent 1)."""
    e, b, t, n, a = 1, 1, 4, 2, 3
    logp = torch.log_softmax(torch.zeros(e, b, t, n, a), -1)
    logq = logp.clone()
    far = torch.tensor([0.98, 0.01, 0.01]).log()
    logq[0, 0, 1, 0] = far
    logq[0, 0, 3, 1] = far
    kl = categorical_kl(logp, logq, torch.ones(e, b, t, n, a, dtype=torch.bool))
    keep = kl_keep_mask(kl, threshold=0.1)
    expected = torch.ones(e, b, t, n)
    expected[0, 0, 1, 0] = expected[0, 0, 3, 1] = 0.0
    assert torch.equal(keep, expected)
    # The joint policy's KL masks the whole step for every agent.
    joint = kl_keep_mask(joint_kl(kl), threshold=0.1)
    assert joint[0, 0].tolist() == [[1, 1], [0, 0], [1, 1], [0, 0]]
    # The masked fraction counts only real entries: step 3 is padding here.
    mask = torch.tensor([[[1.0, 1.0, 1.0, 0.0]]]).unsqueeze(-1).expand(e, b, t, n)
    assert masked_fraction(keep, mask).tolist() == pytest.approx([1 / 6])


def test_mask_zeroes_exactly_the_advantage():
    adv = torch.tensor([[1.5, -2.0, 3.0], [0.5, 4.0, -1.0]]).unsqueeze(-1)  # [T=2, 3, 1]
    keep = torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]).unsqueeze(-1)
    out = masked_advantages(adv, keep)
    assert out.squeeze(-1).tolist() == [[1.5, 0.0, 3.0], [0.0, 4.0, -1.0]]


def test_polyak_update_by_hand():
    src, tgt = EnsembleLinear(1, 2, 1), EnsembleLinear(1, 2, 1)
    with torch.no_grad():
        for p in src.parameters():
            p.fill_(1.0)
        for p in tgt.parameters():
            p.zero_()
    polyak_update_(tgt, src, 0.25)
    assert torch.allclose(tgt.weight, torch.full_like(tgt.weight, 0.25))
    polyak_update_(tgt, src, 0.25)  # 0.75 * 0.25 + 0.25 * 1
    assert torch.allclose(tgt.bias, torch.full_like(tgt.bias, 0.4375))
    polyak_update_(tgt, src, 1.0)  # τ = 1 is a hard copy
    assert torch.allclose(tgt.weight, src.weight)


def _batch(env_id="skirmish/3m", n=4):
    venv = make_vec_env(env_id, n, seed=0)
    info = venv.info
    net = AgentNet(1, info.obs_shape + info.n_actions + info.n_agents, info.n_actions)
    worker = RolloutWorker(venv, net, "softmax", ExplorationConfig(), seed=0)
    return info, EpisodeBatch.from_episodes(worker.collect(n, t_env=0))


def test_learner_starts_with_nothing_masked_and_tracks_the_average_policy():
    info, batch = _batch()
    torch.manual_seed(0)
    learner = CACLearner(CACConfig(polyak_tau=0.5), info.schema(), masked=True)
    before = {k: v.clone() for k, v in learner.agent.state_dict().items()}
    m = learner.step(batch)
    assert m["kl_masked_fraction"] == 0.0 and m["kl_mean"] == pytest.approx(0.0, abs=1e-7)
    for k, v in learner.target_policy.state_dict().items():  # halfway between old and new
        torch.testing.assert_close(v, 0.5 * (before[k] + learner.agent.state_dict()[k]))


def test_fully_masked_batch_leaves_the_actors_unchanged():
    """With every timestep over K and no entropy bonus the policy gradient is exactly zero
    (Adam then moves nothing); the critic still learns. Steps where an agent has a single
    available action (dead units: no-op only) have KL 0 and stay, but carry no gradient."""
    info, batch = _batch()
    torch.manual_seed(0)
    cfg = CACConfig(kl_threshold=1e-9, entropy_coef=0.0)
    learner = CACLearner(cfg, info.schema(), masked=True)
    with torch.no_grad():
        for p in learner.target_policy.parameters():
            p.add_(torch.randn_like(p))
    agent0 = {k: v.clone() for k, v in learner.agent.state_dict().items()}
    critic0 = {k: v.clone() for k, v in learner.critic.state_dict().items()}
    m = learner.step(batch)
    avail = torch.as_tensor(batch.avail_actions[:, :-1]).sum(-1)  # [B, T, N]
    real = torch.as_tensor(batch.filled).unsqueeze(-1).expand_as(avail)
    choice = float(((avail > 1) & real).sum() / real.sum())
    assert 0.3 < choice < 1.0 and m["kl_masked_fraction"] == pytest.approx(choice)
    assert m["grad_norm_policy"] == 0.0
    for k, v in learner.agent.state_dict().items():
        torch.testing.assert_close(v, agent0[k], atol=0, rtol=0)
    assert any(not torch.equal(v, critic0[k]) for k, v in learner.critic.state_dict().items())
    # The same batch with a threshold nothing exceeds does move the actors.
    open_learner = CACLearner(CACConfig(kl_threshold=1e9, entropy_coef=0.0), info.schema())
    open_learner.agent.load_state_dict(agent0)
    assert open_learner.step(batch)["grad_norm_policy"] > 0.0
