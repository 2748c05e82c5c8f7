"""COMA: the counterfactual baseline by hand, the critic's inputs, TD(λ) targets, padding."""

import math

import pytest
import torch

from actors.envs import make_vec_env
from actors.policy import ExplorationConfig
from actors.rollout import RolloutWorker
from buffer_service.episode import EpisodeBatch
from learner.batch import TensorBatch
from learner.coma import COMAConfig, COMALearner, coma_advantages


@pytest.mark.parametrize(
    "q, probs, action, expected",
    [
        ([1.0, 2.0, 3.0], [0.2, 0.3, 0.5], 2, 3.0 - (0.2 + 0.6 + 1.5)),
        ([1.0, 2.0, 3.0], [0.2, 0.3, 0.5], 0, 1.0 - 2.3),
        ([4.0, -1.0], [1.0, 0.0], 0, 0.0),  # deterministic policy: no advantage
        ([5.0, 7.0, 100.0], [0.5, 0.5, 0.0], 1, 1.0),  # unavailable action's Q is ignored
    ],
)
def test_counterfactual_advantage_by_hand(q, probs, action, expected):
    logp = torch.tensor(probs).log()
    adv = coma_advantages(torch.tensor(q), logp, torch.tensor(action))
    assert float(adv) == pytest.approx(expected, abs=1e-6)


def _batch(env_id, n, seed=0):
    venv = make_vec_env(env_id, n, seed=seed)
    info = venv.info
    learner = COMALearner(COMAConfig(), info.schema())
    worker = RolloutWorker(venv, learner.agent, "softmax", ExplorationConfig(), seed=seed)
    return info, learner, EpisodeBatch.from_episodes(worker.collect(n, t_env=0))


def test_critic_input_hides_the_agents_own_action_but_not_the_others():
    info, learner, batch = _batch("skirmish/3m", 2)
    tb = TensorBatch.from_episodes(batch)
    e, b, t, n = tb.shape
    acts = torch.cat([tb.actions, tb.actions[:, :, -1:]], dim=2)
    x = learner.critic_inputs(tb, acts)
    assert x.shape == (e, b, t + 1, n, info.state_shape + info.obs_shape + 2 * n * 9 + n)
    changed = acts.clone()
    changed[:, :, 0, 0] = (changed[:, :, 0, 0] + 1) % info.n_actions
    x2 = learner.critic_inputs(tb, changed)
    # Step 0: agent 0's input is unchanged (own action hidden), agents 1, 2 see the change.
    assert torch.equal(x[:, :, 0, 0], x2[:, :, 0, 0])
    assert not torch.equal(x[:, :, 0, 1], x2[:, :, 0, 1])
    assert not torch.equal(x[:, :, 0, 2], x2[:, :, 0, 2])
    # Step 1: everyone sees it as the previous joint action.
    assert all(not torch.equal(x[:, :, 1, i], x2[:, :, 1, i]) for i in range(n))


def test_critic_regresses_onto_lambda_returns_of_the_target_critic():
    """With zero-initialised last critic layers Q ≡ 0, so the TD(λ) target is the discounted
    reward sum and the critic loss is its masked mean square."""
    _, learner, batch = _batch("matrix/two_step", 3)
    with torch.no_grad():
        for crit in (learner.critic, learner.target_critic.module):
            crit.layers[-1].weight.zero_()
            crit.layers[-1].bias.zero_()
    tb = TensorBatch.from_episodes(batch)
    g = tb.reward.clone()
    gamma, lam = learner.cfg.gamma, learner.cfg.td_lambda
    # two_step: 2 transitions, the second terminal; G1 = r1, G0 = r0 + γ λ G1 (V ≡ 0).
    g[..., 0] = tb.reward[..., 0] + gamma * lam * tb.reward[..., 1]
    expected = (g.pow(2) * tb.mask).sum() / tb.mask.sum()
    m = learner.step(batch)
    assert m["loss_critic"] == pytest.approx(float(expected), rel=1e-5)
    assert m["q_taken_mean"] == 0.0 and m["advantage_abs_mean"] == 0.0


def test_bootstrap_step_uses_the_most_probable_action_and_padding_is_ignored():
    """A time-limit cut bootstraps from Q(s_T, argmax π) whatever the batch's padding."""
    info, learner, batch = _batch("skirmish/3m", 3)
    padded = batch.pad_to(batch.max_t + 5)
    states = []
    for bt in (batch, padded):
        torch.manual_seed(0)
        fresh = COMALearner(COMAConfig(), info.schema())
        fresh.load_state_dict(learner.state_dict())
        metrics = fresh.step(bt)
        states.append((metrics, fresh.state_dict()))
    assert states[0][0]["loss_critic"] == pytest.approx(states[1][0]["loss_critic"], rel=1e-5)
    for k, v in states[0][1]["critic"].items():
        torch.testing.assert_close(v, states[1][1]["critic"][k], atol=1e-6, rtol=1e-5)


def test_entropy_metric_is_uniform_policy_entropy_at_zero_logits():
    _, learner, batch = _batch("matrix/four_game", 4)
    with torch.no_grad():
        learner.agent.out.weight.zero_()
        learner.agent.out.bias.zero_()
    m = learner.step(batch)
    assert m["entropy"] == pytest.approx(math.log(2), abs=1e-6)  # two actions, both available
