"""LRP-epsilon over the critic (`learner.rdn_reference`), its fast per-agent and counterfactual
forms (`learner.rdn_fast.agent_targets`), and RDN's retired variants."""

import pytest
import torch

from learner.critic_inputs import AgentBlocks, agent_blocks, obs_history
from learner.networks import MLP, AgentBlockLinear, EnsembleLinear
from learner.rdn_fast import agent_targets
from learner.rdn_reference import counterfactual_targets, lrp_epsilon, lrp_shares, stabilise


def _random_mlp(seed: int, e: int, d: int, hidden=(64, 64)) -> MLP:
    torch.manual_seed(seed)
    mlp = MLP(e, d, hidden, 1)
    with torch.no_grad():  # larger biases than the default init, to stress bias handling
        for layer in mlp.layers:
            layer.bias.normal_(0.0, 0.5)
    return mlp


def test_the_epsilon_rule_by_hand():
    """One hidden layer, written out: R_k = a_k w2_k q / (z2 + eps sign z2) for the hidden
    units, R_j = x_j sum_k w1_jk R_k / (z1_k + eps sign z1_k) for the inputs, then the
    residual q - sum_j R_j spread over the inputs by |x_j|."""
    mlp = _random_mlp(7, e=1, d=5, hidden=(4,))
    x = torch.randn(1, 3, 5)
    w1, b1 = mlp.layers[0].weight[0], mlp.layers[0].bias[0, 0]
    w2, b2 = mlp.layers[1].weight[0], mlp.layers[1].bias[0, 0]
    eps = 0.1
    want, qs = [], []
    for row in x[0]:
        z1 = row @ w1 + b1
        a1 = torch.relu(z1)
        z2 = a1 @ w2 + b2
        sign2 = 1.0 if z2 >= 0 else -1.0
        r_hidden = a1 * w2[:, 0] * z2[0] / (z2[0] + eps * sign2)
        sign1 = torch.where(z1 >= 0, 1.0, -1.0)
        r_in = row * (w1 @ (r_hidden / (z1 + eps * sign1)))
        r_in = r_in + (z2[0] - r_in.sum()) * row.abs() / row.abs().sum()
        want.append(r_in)
        qs.append(z2[0])
    got, q = lrp_epsilon(mlp, x, eps)
    torch.testing.assert_close(got[0], torch.stack(want), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(q[0], torch.stack(qs))
    assert torch.equal(
        stabilise(torch.tensor([-0.0, 0.0, -2.0]), 0.5), torch.tensor([0.5, 0.5, -2.5])
    )


@pytest.mark.parametrize("seed", range(5))
def test_lrp_epsilon_conserves_exactly(seed):
    mlp = _random_mlp(seed, e=3, d=24)
    x = torch.randn(3, 50, 24)
    rel, out = lrp_epsilon(mlp, x, eps=0.01)
    assert rel.shape == (3, 50, 24) and out.shape == (3, 50)
    # Tolerance: float32 rounding of sums over 24 inputs.
    torch.testing.assert_close(rel.sum(-1), out, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(out, mlp(x).squeeze(-1))


def test_zero_inputs_get_zero_relevance():
    """An agent whose observations are all zero keeps only the relevance of its id and action
    bits."""
    n, obs, a = 3, 5, 4
    block = obs + a + n
    mlp = _random_mlp(1, e=1, d=n * block)
    x = torch.randn(1, 20, n, block)
    x[:, :, 1, :obs] = 0.0  # agent 1 sees nothing
    x = x.view(1, 20, n * block)
    rel, _ = lrp_epsilon(mlp, x, 0.01)
    rel = rel.view(1, 20, n, block)
    assert torch.all(rel[:, :, 1, :obs] == 0.0)
    assert rel[:, :, 1, obs:].abs().sum() > 0  # its action and id bits still count
    shares, _ = lrp_shares(mlp, x, n, 0.01)
    torch.testing.assert_close(shares, rel.sum(-1))


def test_ensemble_members_are_independent():
    """Member 0's relevance does not change when member 1's weights change."""
    mlp = _random_mlp(2, e=2, d=8)
    x = torch.randn(2, 7, 8)
    rel0, _ = lrp_epsilon(mlp, x, 0.01)
    with torch.no_grad():
        for layer in mlp.layers:
            layer.weight[1].normal_()
    rel1, _ = lrp_epsilon(mlp, x, 0.01)
    torch.testing.assert_close(rel0[0], rel1[0])
    assert not torch.allclose(rel0[1], rel1[1])


def _critic(e: int, n: int, block: int, encoder: bool) -> MLP:
    """A 8-8-1 critic, on the concatenated blocks or above a shared per-agent encoder."""
    first = AgentBlockLinear(e, n, block, 6) if encoder else None
    return MLP(e, n * block, (8, 8), 1, first)


def _inputs(o: torch.Tensor, actions: torch.Tensor, a: int) -> tuple[AgentBlocks, torch.Tensor]:
    """The critic input of observations o [E, M, N, O] and actions [E, M, N] (window 1), as
    `AgentBlocks` and dense."""
    x = agent_blocks(obs_history(o[:, None], 1), actions[:, None], a, 1)
    assert isinstance(x, AgentBlocks)
    return x, x.dense()


def test_agent_block_layer_is_the_block_diagonal_dense_layer():
    """Agent i's block reaches only its own units, through weights every agent shares."""
    torch.manual_seed(3)
    layer = AgentBlockLinear(2, 3, 5, 4)
    x = torch.randn(2, 7, 15)
    torch.testing.assert_close(layer(x), torch.baddbmm(layer.bias, x, layer.weight))
    w = layer.weight.view(2, 3, 5, 3, 4)
    for i in range(3):
        torch.testing.assert_close(w[:, i, :, i], layer.block_weight)
        for j in range(3):
            if j != i:
                assert torch.all(w[:, i, :, j] == 0.0)


def test_the_encoders_shares_are_lrp_through_its_dense_block_diagonal_layer():
    """The encoder's shortcut (per-agent sums from its pre-activations, never a product by
    the weights) gives the shares the reference gives on the same critic with its first layer
    written out as the dense block-diagonal layer, from a dense or an AgentBlocks input."""
    torch.manual_seed(6)
    e, m, n, a, obs = 2, 7, 3, 4, 5
    block = obs + a + n
    encoded = _critic(e, n, block, encoder=True)
    first = EnsembleLinear(e, n * block, encoded.layers[0].out_features)
    dense = MLP(e, n * block, (8, 8), 1, first)
    with torch.no_grad():
        first.weight.copy_(encoded.layers[0].weight)
        first.bias.copy_(encoded.layers[0].bias)
        for k in (1, 2, 3):
            dense.layers[k].load_state_dict(encoded.layers[k].state_dict())
    o = torch.randn(e, m, n, obs)
    o[0, 2, 1] = 0.0  # a dead agent's observation
    acts = torch.randint(0, a, (e, m, n))
    blocks, x = _inputs(o, acts, a)
    want, q_want = lrp_shares(dense, x, n, 0.01)
    for given in (x, blocks):
        got = agent_targets(encoded, given, acts, None, 0.01, obs)
        torch.testing.assert_close(got.q, q_want)
        torch.testing.assert_close(got.shares, want, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("encoder", [False, True], ids=["dense_first", "agent_encoder"])
def test_counterfactual_targets_on_the_kept_entries_are_the_references(encoder):
    """With `keep`, the kept entries are the share plus the critic's difference on those
    counterfactuals (`counterfactual_targets`: one critic pass each) and every other entry is
    the share alone; members may keep different numbers, or none."""
    torch.manual_seed(5)
    e, m, n, a, obs = 3, 6, 3, 5, 4
    mlp = _critic(e, n, obs + a + n, encoder)
    o = torch.randn(e, m, n, obs)
    acts = torch.randint(0, a, (e, m, n))
    blocks, x = _inputs(o, acts, a)
    keep = torch.rand(e, m, n, a) < 0.4
    keep[1] = False  # one member with nothing to compute
    got = agent_targets(mlp, blocks, acts, keep, 0.01, obs)
    shares, q = lrp_shares(mlp, x, n, 0.01)
    want = counterfactual_targets(mlp, x, shares, q, obs, a)
    torch.testing.assert_close(got.every[keep], want[keep], atol=1e-5, rtol=1e-5)
    share = got.shares.unsqueeze(-1).expand_as(got.every)
    assert torch.equal(got.every[~keep], share[~keep])
    everything = agent_targets(mlp, blocks, acts, torch.ones_like(keep), 0.01, obs)
    torch.testing.assert_close(everything.every, want, atol=1e-5, rtol=1e-5)


def test_rdn_with_an_agent_encoder_steps_and_rejects_a_negative_width():
    from actors.envs.registry import make_vec_env
    from cluster.bench.update import record_batch
    from learner.rdn import RDNConfig, RDNLearner

    with pytest.raises(ValueError, match="critic_agent_encoder"):
        RDNConfig(critic_agent_encoder=-1).validate()
    cfg = RDNConfig(critic_agent_encoder=16, critic_hidden=(8,), agent_targets="counterfactual")
    cfg.validate()
    learner = RDNLearner(cfg, make_vec_env("skirmish/3m", 1).info.schema())
    before = learner.critic.layers[0].block_weight.detach().clone()
    metrics = learner.step(record_batch("skirmish/3m", 4, 1))
    assert metrics["lrp_conservation_gap"] < 1e-3
    assert not torch.equal(before, learner.critic.layers[0].block_weight)


def test_retired_variants_name_the_commit_that_had_them_and_old_configs_still_load():
    """A saved config.yaml from before the variants were deleted resumes when its retired
    keys hold what RDN computes; asking for a deleted variant is an error naming commit
    828260c."""
    from cluster.config.schema import ConfigError
    from cluster.config.train import build_train_config, load_train_config

    saved = load_train_config("rdn", "skirmish/3m").to_yaml_dict()
    old = {"next_action": "greedy", "split_critic": "online", "lrp_rule": "eps_residual"}
    old |= {"split_actions": "taken", "lrp_reference": "zero", "joint_max_limit": 1024}
    assert build_train_config({**saved, "algo": {**saved["algo"], **old}}).algo == (
        build_train_config(saved).algo
    )
    with pytest.raises(ConfigError, match="next_action='local_max' is a retired RDN variant"):
        load_train_config("rdn", "skirmish/3m", [], ["algo.next_action=local_max"])
    with pytest.raises(ConfigError, match="commit 828260c"):
        load_train_config("rdn", "skirmish/3m", [], ["algo.lrp_rule=eps"])
    with pytest.raises(ConfigError, match="'all_actions' is not one of"):
        load_train_config("rdn", "skirmish/3m", [], ["algo.agent_targets=all_actions"])
