"""LRP over the critic MLP: conservation, per-agent blocks, zero inputs."""

import pytest
import torch

from learner.lrp import (
    LRP_RULES,
    agent_relevance,
    agent_relevance_all_actions,
    critic_all_actions,
    lrp_difference,
    lrp_epsilon,
)
from learner.networks import MLP


def _random_mlp(seed: int, e: int, d: int, hidden=(64, 64)) -> MLP:
    torch.manual_seed(seed)
    mlp = MLP(e, d, hidden, 1)
    with torch.no_grad():  # larger biases than the default init, to stress bias handling
        for layer in mlp.layers:
            layer.bias.normal_(0.0, 0.5)
    return mlp


@pytest.mark.parametrize("seed", range(10))
def test_eps_residual_conserves_exactly(seed):
    mlp = _random_mlp(seed, e=3, d=24)
    x = torch.randn(3, 50, 24)
    rel, out = lrp_epsilon(mlp, x, eps=0.01, rule="eps_residual")
    assert rel.shape == (3, 50, 24) and out.shape == (3, 50)
    # Tolerance: float32 rounding of sums over 24 inputs.
    torch.testing.assert_close(rel.sum(-1), out, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(out, mlp(x).squeeze(-1))


@pytest.mark.parametrize("seed", range(5))
def test_bias_rules_lose_relevance_that_the_residual_rule_keeps(seed):
    """Plain LRP-eps with biases in the denominator does not conserve; this is why the default
    redistributes the residual. The no-bias denominator conserves up to what the output bias
    and eps take."""
    mlp = _random_mlp(seed, e=1, d=16)
    x = torch.randn(1, 200, 16)
    rel_eps, out = lrp_epsilon(mlp, x, rule="eps")
    assert (rel_eps.sum(-1) - out).abs().mean() > 1e-2
    rel_nb, out = lrp_epsilon(mlp, x, eps=1e-6, rule="eps_nobias")
    # With eps -> 0 each ReLU layer passes its whole relevance down, except through units whose
    # input contribution is near zero (the stabiliser then dominates): conservation holds for
    # the typical input (median) and on average far better than with the bias in the denominator.
    gap_nb = (rel_nb.sum(-1) - out).abs()
    gap_eps = (rel_eps.sum(-1) - out).abs()
    assert gap_nb.median() < 1e-3 * out.abs().mean() + 1e-5
    assert gap_nb.mean() < 0.05 * gap_eps.mean()


def test_grad_x_input_equals_output_for_bias_free_relu_net():
    """For a ReLU net without biases f(x) = sum_j x_j df/dx_j (Euler), a sanity check of the
    gradient-times-input baseline."""
    mlp = _random_mlp(0, e=2, d=10)
    with torch.no_grad():
        for layer in mlp.layers:
            layer.bias.zero_()
    x = torch.randn(2, 30, 10)
    rel, out = lrp_epsilon(mlp, x, rule="grad_x_input")
    torch.testing.assert_close(rel.sum(-1), out, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("rule", LRP_RULES)
def test_zero_inputs_get_zero_relevance(rule):
    """An agent whose observations are all zero keeps only the relevance of its id and action
    bits (every rule gives a zero input exactly zero relevance)."""
    n, obs, a = 3, 5, 4
    block = obs + a + n
    mlp = _random_mlp(1, e=1, d=n * block)
    x = torch.randn(1, 20, n, block)
    x[:, :, 1, :obs] = 0.0  # agent 1 sees nothing
    x = x.view(1, 20, n * block)
    rel, _ = lrp_epsilon(mlp, x, rule=rule)
    rel = rel.view(1, 20, n, block)
    assert torch.all(rel[:, :, 1, :obs] == 0.0)
    assert rel[:, :, 1, obs:].abs().sum() > 0  # its action and id bits still count


def test_agent_relevance_sums_each_block():
    rel = torch.arange(2 * 3 * 12, dtype=torch.float32).view(2, 3, 12)
    per_agent = agent_relevance(rel, n_agents=3)
    expected = rel.view(2, 3, 3, 4).sum(-1)
    torch.testing.assert_close(per_agent, expected)
    assert per_agent[0, 0].tolist() == [0 + 1 + 2 + 3, 4 + 5 + 6 + 7, 8 + 9 + 10 + 11]
    with pytest.raises(ValueError, match="multiple of n_agents"):
        agent_relevance(torch.zeros(1, 1, 10), n_agents=3)


def test_ensemble_members_are_independent():
    """Member 0's relevance does not change when member 1's weights change."""
    mlp = _random_mlp(2, e=2, d=8)
    x = torch.randn(2, 7, 8)
    rel0, _ = lrp_epsilon(mlp, x)
    with torch.no_grad():
        for layer in mlp.layers:
            layer.weight[1].normal_()
    rel1, _ = lrp_epsilon(mlp, x)
    torch.testing.assert_close(rel0[0], rel1[0])
    assert not torch.allclose(rel0[1], rel1[1])


def _blocks(o: torch.Tensor, actions: torch.Tensor, a: int) -> torch.Tensor:
    """Critic inputs from observations o [E, M, N, O] and actions [E, M, N]: per agent
    [obs, action one-hot, id one-hot], blocks laid end to end."""
    e, m, n, _ = o.shape
    ids = torch.eye(n).expand(e, m, n, n)
    onehot = torch.nn.functional.one_hot(actions, a).float()
    return torch.cat([o, onehot, ids], -1).reshape(e, m, -1)


@pytest.mark.parametrize("rule", ["eps_residual", "eps", "eps_nobias"])
def test_all_actions_shares_match_one_lrp_call_per_counterfactual(rule):
    """The first-layer shortcut gives exactly what N·A separate LRP calls give."""
    torch.manual_seed(0)
    e, m, n, a, obs = 2, 5, 3, 4, 6
    block = obs + a + n
    mlp = MLP(e, n * block, (16, 8), 1)
    o = torch.randn(e, m, n, obs)
    acts = torch.randint(0, a, (e, m, n))

    got = agent_relevance_all_actions(mlp, _blocks(o, acts, a), acts, n, obs, a, 0.01, rule)
    for i in range(n):
        for u in range(a):
            alt = acts.clone()
            alt[..., i] = u
            rel, _ = lrp_epsilon(mlp, _blocks(o, alt, a), 0.01, rule)
            torch.testing.assert_close(got[..., i, u], agent_relevance(rel, n)[..., i])


def test_lrp_difference_conserves_and_ignores_inputs_at_their_reference():
    torch.manual_seed(1)
    mlp = MLP(2, 6, (16, 8), 1)
    x = torch.randn(2, 7, 6)
    ref = x.clone()
    ref[..., 4:] = 0.0  # only the last two features deviate from the reference
    rel, delta = lrp_difference(mlp, x, ref)
    torch.testing.assert_close(delta, (mlp(x) - mlp(ref)).squeeze(-1))
    torch.testing.assert_close(rel.sum(-1), delta)  # exact conservation of the difference
    assert torch.all(rel[..., :4] == 0.0)


def test_lrp_difference_of_a_linear_map_is_each_inputs_own_term():
    """Without active nonlinearity the split is exact: R_j = w_j (x_j - ref_j)."""
    mlp = MLP(1, 3, (4,), 1)
    with torch.no_grad():
        mlp.layers[0].weight.copy_(torch.eye(3, 4).unsqueeze(0))
        mlp.layers[0].bias.fill_(10.0)  # every hidden unit stays active
        mlp.layers[1].weight.copy_(torch.tensor([[[2.0], [-1.0], [0.5], [0.0]]]))
    x = torch.tensor([[[1.0, 2.0, 3.0]]])
    ref = torch.tensor([[[0.0, 0.0, 1.0]]])
    rel, _ = lrp_difference(mlp, x, ref, eps=1e-9)
    torch.testing.assert_close(rel, torch.tensor([[[2.0, -2.0, 1.0]]]), atol=1e-5, rtol=0)


@pytest.mark.parametrize("reference", ["zero", "no_actions"])
@pytest.mark.parametrize("targets", ["taken", "all_actions", "counterfactual"])
def test_rdn_agent_targets_add_up_to_the_critic_value(reference, targets):
    """Both splits conserve: the agents' targets sum to Q_c(x); RDN steps with every option."""
    from actors.envs.registry import make_vec_env
    from buffer_service.episode import EpisodeBatch
    from cluster.bench.update import record_batch
    from learner.rdn import RDNConfig, RDNLearner

    if targets == "all_actions" and reference != "zero":
        with pytest.raises(ValueError, match="needs lrp_reference=zero"):
            RDNConfig(agent_targets=targets, lrp_reference=reference).validate()
        return
    cfg = RDNConfig(agent_targets=targets, lrp_reference=reference)
    cfg.validate()
    schema = make_vec_env("skirmish/3m", 1).info.schema()
    learner = RDNLearner(cfg, schema)
    batch = record_batch("skirmish/3m", 4, 1)
    assert isinstance(batch, EpisodeBatch)
    metrics = learner.step(batch)
    assert metrics["lrp_conservation_gap"] < 1e-3


def _critic(e: int, n: int, block: int, encoder: bool) -> MLP:
    """A 8-8-1 critic, on the concatenated blocks or above a shared per-agent encoder."""
    from learner.networks import AgentBlockLinear

    first = AgentBlockLinear(e, n, block, 6) if encoder else None
    return MLP(e, n * block, (8, 8), 1, first)


@pytest.mark.parametrize("encoder", [False, True], ids=["dense", "agent_encoder"])
def test_critic_all_actions_is_the_critic_on_each_counterfactual(encoder):
    torch.manual_seed(2)
    e, m, n, a, obs = 2, 4, 3, 5, 4
    block = obs + a + n
    mlp = _critic(e, n, block, encoder)
    o = torch.randn(e, m, n, obs)
    acts = torch.randint(0, a, (e, m, n))

    got = critic_all_actions(mlp, _blocks(o, acts, a), acts, n, obs, a)
    for i in range(n):
        for u in range(a):
            alt = acts.clone()
            alt[..., i] = u
            torch.testing.assert_close(got[..., i, u], mlp(_blocks(o, alt, a)).squeeze(-1))


@pytest.mark.parametrize("encoder", [False, True], ids=["dense", "agent_encoder"])
def test_critic_all_actions_on_selected_variants_only(encoder):
    """With `keep`, the kept entries are the critic on those counterfactuals and every other
    entry is the critic's value of x itself; members may keep different numbers."""
    torch.manual_seed(5)
    e, m, n, a, obs = 3, 6, 3, 5, 4
    mlp = _critic(e, n, obs + a + n, encoder)
    o = torch.randn(e, m, n, obs)
    acts = torch.randint(0, a, (e, m, n))
    x = _blocks(o, acts, a)
    keep = torch.rand(e, m, n, a) < 0.4
    keep[1] = False  # one member with nothing to compute
    full = critic_all_actions(mlp, x, acts, n, obs, a)
    got = critic_all_actions(mlp, x, acts, n, obs, a, keep)
    torch.testing.assert_close(got[keep], full[keep])
    q_x = mlp(x).view(e, m, 1, 1).expand_as(got)
    torch.testing.assert_close(got[~keep], q_x[~keep])
    none = critic_all_actions(mlp, x, acts, n, obs, a, torch.zeros_like(keep))
    torch.testing.assert_close(none, q_x)
    # Q_c(x) handed in (as RDN does from its LRP pass) fills the entries not computed: the
    # ones not kept and the taken actions'
    value = torch.randn(e, m)
    given = critic_all_actions(mlp, x, acts, n, obs, a, keep, value=value)
    taken = torch.nn.functional.one_hot(acts, a).bool()
    moved = keep & ~taken
    torch.testing.assert_close(given[moved], full[moved])
    assert torch.equal(given[~moved], value.view(e, m, 1, 1).expand_as(got)[~moved])


def _encoder_mlp(e: int, n: int, block: int) -> MLP:
    from learner.networks import AgentBlockLinear

    return MLP(e, n * block, (8,), 1, AgentBlockLinear(e, n, block, 6))


def test_agent_block_layer_is_the_block_diagonal_dense_layer():
    """Agent i's block reaches only its own units, through weights every agent shares."""
    from learner.networks import AgentBlockLinear

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


def test_lrp_through_an_agent_encoder_conserves_and_matches_the_shortcuts():
    torch.manual_seed(4)
    e, m, n, a, obs = 2, 5, 3, 4, 6
    block = obs + a + n
    mlp = _encoder_mlp(e, n, block)
    o = torch.randn(e, m, n, obs)
    acts = torch.randint(0, a, (e, m, n))
    x = _blocks(o, acts, a)
    rel, q = lrp_epsilon(mlp, x)
    torch.testing.assert_close(rel.sum(-1), q)
    every = agent_relevance_all_actions(mlp, x, acts, n, obs, a)
    values = critic_all_actions(mlp, x, acts, n, obs, a)
    for i in range(n):
        alt = acts.clone()
        alt[..., (i + 1) % n] = (acts[..., (i + 1) % n] + 1) % a
        u = alt[..., (i + 1) % n]
        rel_alt, q_alt = lrp_epsilon(mlp, _blocks(o, alt, a))
        got = every[..., (i + 1) % n, :].gather(-1, u.unsqueeze(-1)).squeeze(-1)
        torch.testing.assert_close(got, agent_relevance(rel_alt, n)[..., (i + 1) % n])
        got_q = values[..., (i + 1) % n, :].gather(-1, u.unsqueeze(-1)).squeeze(-1)
        torch.testing.assert_close(got_q, q_alt)


@pytest.mark.parametrize("rule", ["eps_residual", "eps", "eps_nobias", "grad_x_input"])
def test_lrp_through_an_agent_encoder_is_lrp_through_its_dense_block_diagonal_layer(rule):
    """The encoder's shortcut (per-agent sums from its pre-activations, never a product by
    the weights) gives the relevance that the plain dense path gives on the same critic with
    its first layer written out as the dense block-diagonal layer, per agent and per feature;
    from the AgentBlocks input RDN passes too."""
    from learner.batch import AgentBlocks, agent_blocks, obs_history
    from learner.networks import EnsembleLinear

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
    want, q_want = lrp_epsilon(dense, _blocks(o, acts, a), rule=rule)
    lazy = agent_blocks(obs_history(o[:, None], 1), acts[:, None], a, 1)
    assert isinstance(lazy, AgentBlocks)
    for x in (_blocks(o, acts, a), lazy):
        got, q = lrp_epsilon(encoded, x, rule=rule)
        # z1 - b against x @ W (eps_nobias): the same sums rounded differently
        close = {"rtol": 1e-4, "atol": 1e-4}
        torch.testing.assert_close(q, q_want)
        torch.testing.assert_close(agent_relevance(got, n), agent_relevance(want, n), **close)
        torch.testing.assert_close(got + 0.0, want, **close)  # the dense values, materialised


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


def test_rdn_local_max_next_action_is_the_best_available_single_agent_deviation():
    """next_action "local_max": among the greedy joint action and every joint action moving one
    agent's action, the online critic's best, never an unavailable action; brute force."""
    from actors.envs.registry import make_vec_env
    from cluster.bench.update import record_batch
    from learner.batch import TensorBatch, obs_history
    from learner.rdn import RDNConfig, RDNLearner

    torch.manual_seed(0)
    cfg = RDNConfig(next_action="local_max", critic_hidden=(16, 16))
    schema = make_vec_env("skirmish/3m", 1).info.schema()
    learner = RDNLearner(cfg, schema)
    tb = TensorBatch.from_episodes(record_batch("skirmish/3m", 3, 1))
    hist = obs_history(tb.obs, cfg.obs_window)[:, :, 1:]
    avail = tb.avail[:, :, 1:]
    e, b, t, n = tb.actions.shape
    a = schema.n_actions
    # a random available action for every agent (padding steps make the no-op available)
    greedy = torch.multinomial(avail.reshape(-1, a).float(), 1).view(e, b, t, n)
    with torch.no_grad():
        got = learner._best_deviation(hist, greedy, avail)
        value = learner.critic(learner.critic_inputs(hist, got)).view(e, b, t)
        best = learner.critic(learner.critic_inputs(hist, greedy)).view(e, b, t)
        for i in range(n):
            for u in range(a):
                alt = greedy.clone()
                alt[..., i] = u
                q = learner.critic(learner.critic_inputs(hist, alt)).view(e, b, t)
                best = torch.where(avail[..., i, u], torch.maximum(best, q), best)
    torch.testing.assert_close(value, best)
    assert avail.gather(-1, got.unsqueeze(-1)).all()
    assert ((got != greedy).sum(-1) <= 1).all()
    metrics = learner.step(record_batch("skirmish/3m", 4, 1))
    assert metrics["lrp_conservation_gap"] < 1e-3


def assert_counterfactual_targets(learner, hist, acts, shares, ok, got):
    """By brute force: at every real step and available action u of agent i, the target `got`
    is agent i's LRP share at the joint action `acts` plus Q_c(acts with a_i = u) - Q_c(acts)."""
    e, b, t, n = acts.shape
    shares = shares.view(e, b, t, n)
    with torch.no_grad():
        q = learner.critic(learner.critic_inputs(hist, acts)).view(e, b, t)
        for i in range(n):
            for u in range(learner.info.n_actions):
                alt = acts.clone()
                alt[..., i] = u
                q_alt = learner.critic(learner.critic_inputs(hist, alt)).view(e, b, t)
                want = shares[..., i] + q_alt - q
                sel = ok[..., i, u]
                torch.testing.assert_close(got[..., i, u][sel], want[sel], atol=1e-5, rtol=1e-5)


def test_rdn_counterfactual_targets_are_the_share_plus_the_critics_difference():
    """agent_targets "counterfactual" on a skirmish batch, by brute force: at every real step
    and available action u of agent i, the target is agent i's LRP share plus
    Q_c(x with a_i = u) - Q_c(x)."""
    from actors.envs.registry import make_vec_env
    from cluster.bench.update import record_batch
    from learner.batch import TensorBatch, obs_history
    from learner.rdn import RDNConfig, RDNLearner

    torch.manual_seed(1)
    cfg = RDNConfig(agent_targets="counterfactual", critic_hidden=(16, 16))
    schema = make_vec_env("skirmish/3m", 1).info.schema()
    learner = RDNLearner(cfg, schema)
    tb = TensorBatch.from_episodes(record_batch("skirmish/3m", 3, 1))
    hist = obs_history(tb.obs, cfg.obs_window)[:, :, :-1]
    e, b, t, n = tb.actions.shape
    ok = tb.avail[:, :, :-1] & tb.mask.bool()[..., None, None]
    with torch.no_grad():
        x = learner.critic_inputs(hist, tb.actions)
        shares, q, first = learner._split(x)  # first: the critic's first layer, from LRP
        assert first is not None
        got = learner._every_action_targets(x, tb.actions, shares.view(e, b, t, n), q, ok, first)
        assert_counterfactual_targets(learner, hist, tb.actions, shares, ok, got)


def test_rdn_split_critic_target_splits_the_frozen_copy_and_agent_lr_scale_sets_its_rate():
    """split_critic "target": the agents' targets come from the target critic, so moving the
    online critic leaves them unchanged (and with "online" it changes them); agent_lr_scale
    multiplies the agents' learning rate only; bad values name the key."""
    from actors.envs.registry import make_vec_env
    from cluster.bench.update import record_batch
    from learner.batch import TensorBatch, obs_history
    from learner.rdn import RDNConfig, RDNLearner

    with pytest.raises(ValueError, match="split_critic"):
        RDNConfig(split_critic="newest").validate()
    with pytest.raises(ValueError, match="agent_lr_scale"):
        RDNConfig(agent_lr_scale=0.0).validate()
    schema = make_vec_env("skirmish/3m", 1).info.schema()
    tb = TensorBatch.from_episodes(record_batch("skirmish/3m", 3, 1))
    hist = obs_history(tb.obs, 4)[:, :, :-1]
    shares = {}
    for which in ("online", "target"):
        torch.manual_seed(3)
        cfg = RDNConfig(split_critic=which, critic_hidden=(16, 16), lr=0.002, agent_lr_scale=0.25)
        cfg.validate()
        learner = RDNLearner(cfg, schema)
        assert learner.agent_updater.optimiser.param_groups[0]["lr"] == pytest.approx(0.0005)
        assert learner.critic_updater.optimiser.param_groups[0]["lr"] == pytest.approx(0.002)
        x = learner.critic_inputs(hist, tb.actions)
        before, _ = learner.agent_targets(x)
        with torch.no_grad():
            for p in learner.critic.parameters():
                p.add_(0.1 * torch.randn_like(p))
        after, q = learner.agent_targets(x)
        shares[which] = (before, after)
        with torch.no_grad():
            want = learner.split_module(x).squeeze(-1)
        torch.testing.assert_close(q, want)
    assert not torch.allclose(*shares["online"])
    torch.testing.assert_close(*shares["target"])


def test_rdn_split_actions_greedy_centres_the_targets_on_the_agents_greedy_joint_action():
    """split_actions "greedy": the joint action the targets are split at is every agent's
    greedy available action (not the taken one), and agent i's counterfactual target for u is
    its LRP share there plus Q_c(u, greedy_-i) - Q_c(greedy), by brute force; with "taken"
    the taken actions come back unchanged; the option refuses taken-action targets."""
    from actors.envs.registry import make_vec_env
    from cluster.bench.update import record_batch
    from learner.batch import TensorBatch, obs_history
    from learner.rdn import RDNConfig, RDNLearner

    with pytest.raises(ValueError, match="split_actions"):
        RDNConfig(split_actions="best").validate()
    with pytest.raises(ValueError, match="split_actions=greedy needs agent_targets"):
        RDNConfig(split_actions="greedy", agent_targets="taken").validate()
    torch.manual_seed(2)
    schema = make_vec_env("skirmish/3m", 1).info.schema()
    tb = TensorBatch.from_episodes(record_batch("skirmish/3m", 3, 1))
    e, b, t, n = tb.actions.shape
    a = schema.n_actions
    avail = tb.avail[:, :, :-1]
    qs = torch.randn(e, b, t, n, a)
    taken = RDNLearner(RDNConfig(agent_targets="counterfactual"), schema)
    assert taken.split_joint_action(qs, tb.actions, avail) is tb.actions
    cfg = RDNConfig(agent_targets="counterfactual", split_actions="greedy", critic_hidden=(16, 16))
    cfg.validate()
    learner = RDNLearner(cfg, schema)
    greedy = learner.split_joint_action(qs, tb.actions, avail)
    real = tb.mask.bool()
    assert avail.gather(-1, greedy.unsqueeze(-1)).squeeze(-1)[real].all()
    best = qs.masked_fill(~avail, float("-inf")).max(-1).values
    torch.testing.assert_close(qs.gather(-1, greedy.unsqueeze(-1)).squeeze(-1)[real], best[real])
    assert (greedy != tb.actions)[real].any()
    hist = obs_history(tb.obs, cfg.obs_window)[:, :, :-1]
    ok = avail & real[..., None, None]
    with torch.no_grad():
        x = learner.critic_inputs(hist, greedy)
        shares, q, first = learner._split(x)
        got = learner._every_action_targets(x, greedy, shares.view(e, b, t, n), q, ok, first)
        assert_counterfactual_targets(learner, hist, greedy, shares, ok, got)
    metrics = learner.step(record_batch("skirmish/3m", 4, 1))
    assert metrics["lrp_conservation_gap"] < 1e-3
