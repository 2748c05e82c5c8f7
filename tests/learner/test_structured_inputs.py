"""The structured network inputs (the agents' `AgentInputs`, RDN's `ObsWindows` and
`AgentBlocks`, `block_preactivation`, LRP's per-agent sums by `block_dot`) compute what the
straightforward dense implementation computes.

The straightforward versions are kept here, as they were before the optimisation: agent
inputs and windows by concatenation, the critic input by concatenating one-hots, LRP-ε over
the dense input, the unroll over the dense inputs."""

import pytest
import torch
from torch.nn import functional as F

from learner.batch import (
    AgentBlocks,
    AgentInputs,
    ObsWindows,
    agent_blocks,
    agent_blocks_dense,
    agent_inputs,
    obs_history,
)
from learner.lrp import LRP_RULES, BlockRelevance, agent_relevance, lrp_epsilon
from learner.networks import MLP, AgentBlockLinear, AgentNet, unroll


def reference_agent_inputs(obs: torch.Tensor, actions: torch.Tensor, a: int) -> torch.Tensor:
    e, b, tp, n, _ = obs.shape
    last = torch.zeros(e, b, tp, n, a)
    k = min(tp - 1, actions.shape[2])
    if k > 0:
        last[:, :, 1 : k + 1] = F.one_hot(actions[:, :, :k], a).float()
    ids = torch.eye(n).expand(e, b, tp, n, n)
    return torch.cat([obs, last, ids], dim=-1)


def reference_unroll(agent: AgentNet, inputs: torch.Tensor) -> torch.Tensor:
    """The agent called step by step on the dense inputs."""
    e, b, tp, n, d = inputs.shape
    h = agent.init_hidden(e, b * n)
    outs = []
    for t in range(tp):
        q, h = agent(inputs[:, :, t].reshape(e, b * n, d), h)
        outs.append(q.view(e, b, n, -1))
    return torch.stack(outs, dim=2)


def reference_obs_history(obs: torch.Tensor, window: int) -> torch.Tensor:
    pad = obs.new_zeros(*obs.shape[:2], window - 1, *obs.shape[3:])
    padded = torch.cat([pad, obs], dim=2)
    tp = obs.shape[2]
    return torch.cat([padded[:, :, i : i + tp] for i in range(window)], dim=-1)


def reference_critic_inputs(hist: torch.Tensor, actions: torch.Tensor, a: int) -> torch.Tensor:
    e, b, tp, n, _ = hist.shape
    ids = torch.eye(n).expand(e, b, tp, n, n)
    x = torch.cat([hist, F.one_hot(actions, a).float(), ids], dim=-1)
    return x.reshape(e, b * tp, -1)


def _stabilise(z, eps):
    return z + eps * torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))


def reference_lrp(mlp: MLP, x: torch.Tensor, eps: float, rule: str):
    """LRP over the dense input, per feature (learner/lrp.py before AgentBlocks)."""
    if rule == "grad_x_input":
        xg = x.detach().requires_grad_(True)
        out = mlp(xg).squeeze(-1)
        (grad,) = torch.autograd.grad(out.sum(), xg)
        return (grad * xg).detach(), out.detach()
    with torch.no_grad():
        acts = [x]
        h = x
        for layer in mlp.layers[:-1]:
            h = F.relu(torch.baddbmm(layer.bias, h, layer.weight))
            acts.append(h)
        out = torch.baddbmm(mlp.layers[-1].bias, h, mlp.layers[-1].weight)
        relevance = out
        for layer, a in zip(reversed(mlp.layers), reversed(acts), strict=True):
            z = torch.bmm(a, layer.weight)
            if rule != "eps_nobias":
                z = z + layer.bias
            relevance = a * torch.bmm(relevance / _stabilise(z, eps), layer.weight.transpose(1, 2))
        out = out.squeeze(-1)
        if rule == "eps_residual":
            weight = x.abs()
            total = weight.sum(-1, keepdim=True)
            share = torch.where(total > 0, weight / total.clamp_min(1e-12), 0.0)
            relevance = relevance + (out - relevance.sum(-1)).unsqueeze(-1) * share
    return relevance, out


def _close(got: torch.Tensor, want: torch.Tensor, scale: float = 1e-5) -> None:
    """float32 agreement up to summation order (LRP-ε without bias amplifies rounding near
    z = 0, so the tolerance follows the values' size)."""
    tol = scale * (1.0 + float(want.detach().abs().max()))
    torch.testing.assert_close(got, want, atol=tol, rtol=1e-4)


def _batch(seed: int = 0, e: int = 2, b: int = 3, t: int = 7, n: int = 4, o: int = 5, a: int = 4):
    """Observations with dead agents (all-zero rows from some step on) and padding."""
    gen = torch.Generator().manual_seed(seed)
    obs = torch.randn(e, b, t + 1, n, o, generator=gen)
    obs[:, 0, 4:, 1] = 0.0  # agent 1 dies in episode 0
    obs[:, 1, 5:] = 0.0  # episode 1 ends early (padding)
    obs[1, 2, :, 2] = 0.0  # member 1's agent 2 never sees anything in episode 2
    actions = torch.randint(0, a, (e, b, t + 1, n), generator=gen)
    return obs, actions


def _mlp(e: int, d: int, seed: int = 0, encoder_agents: int = 0) -> MLP:
    """A 16-8-1 critic; with encoder_agents = N, above a shared 6-unit per-agent encoder."""
    torch.manual_seed(seed)
    n = encoder_agents
    first = AgentBlockLinear(e, n, d // n, 6) if n else None
    mlp = MLP(e, d, (16, 8), 1, first)
    with torch.no_grad():
        for p in mlp.parameters():
            if p.shape[-2] == 1:  # the biases
                p.normal_(0.0, 0.5)
    return mlp


@pytest.mark.parametrize("window", [1, 2, 4])
def test_obs_history_holds_the_concatenated_windows_and_slices_stay_lazy(window):
    obs, _ = _batch()
    hist = obs_history(obs, window)
    ref = reference_obs_history(obs, window)
    assert isinstance(hist, ObsWindows) and hist.shape == ref.shape
    torch.testing.assert_close(hist, ref, rtol=0, atol=0)
    for sl in (slice(None, -1), slice(1, None), slice(2, 5), slice(-3, None)):
        part = hist[:, :, sl]
        assert isinstance(part, ObsWindows)
        torch.testing.assert_close(part, ref[:, :, sl], rtol=0, atol=0)
        torch.testing.assert_close(part[:, :, 1:], ref[:, :, sl][:, :, 1:], rtol=0, atol=0)
    assert type(hist[0]) is torch.Tensor  # any other indexing is dense
    torch.testing.assert_close(hist[0], ref[0], rtol=0, atol=0)


@pytest.mark.parametrize("encoder", [False, True], ids=["dense_first", "agent_encoder"])
@pytest.mark.parametrize("window", [1, 3])
@pytest.mark.parametrize("part", ["now", "next"])
def test_critic_forward_and_gradients_match_the_dense_input(window, part, encoder):
    obs, actions = _batch(window)
    a = 4
    hist = obs_history(obs, window)
    sl = slice(None, -1) if part == "now" else slice(1, None)
    acts = actions[:, :, :-1] if part == "now" else actions[:, :, 1:]
    x = agent_blocks(hist[:, :, sl], acts, a, window)
    dense = reference_critic_inputs(reference_obs_history(obs, window)[:, :, sl], acts, a)
    assert isinstance(x, AgentBlocks) and x.shape == dense.shape
    mlp = _mlp(2, dense.shape[-1], encoder_agents=4 if encoder else 0)
    y, y_ref = mlp(x), mlp(dense)
    _close(y, y_ref)
    grads = torch.autograd.grad(y.pow(2).sum(), list(mlp.parameters()))
    grads_ref = torch.autograd.grad(y_ref.pow(2).sum(), list(mlp.parameters()))
    for g, g_ref in zip(grads, grads_ref, strict=True):
        _close(g, g_ref)
    torch.testing.assert_close(x.dense(), dense, rtol=0, atol=0)
    torch.testing.assert_close(x.block_l1(), dense.abs().view(2, -1, 4, x.block).sum(-1))


@pytest.mark.parametrize("rule", LRP_RULES)
def test_lrp_of_agent_blocks_matches_lrp_of_the_dense_input(rule):
    obs, actions = _batch(3)
    window, a, n = 4, 4, 4
    hist = obs_history(obs, window)[:, :, :-1]
    x = agent_blocks(hist, actions[:, :, :-1], a, window)
    dense = reference_critic_inputs(hist.contiguous(), actions[:, :, :-1], a)
    mlp = _mlp(2, dense.shape[-1], seed=1)
    rel, q = lrp_epsilon(mlp, x, 0.01, rule)
    rel_ref, q_ref = reference_lrp(mlp, dense, 0.01, rule)
    assert isinstance(rel, BlockRelevance)
    _close(q, q_ref)
    _close(agent_relevance(rel, n), agent_relevance(rel_ref, n))
    _close(rel.dense(), rel_ref)  # the per-feature values, if anyone asks for them
    if rule == "eps_residual":  # conserves
        _close(agent_relevance(rel, n).sum(-1), q)


@pytest.mark.parametrize("build_c", [0.0, float("inf")])  # c summed / s gathered per pair
@pytest.mark.parametrize("window", [1, 4])
def test_block_dot_is_each_agents_dense_contribution_dotted_with_s(window, build_c, monkeypatch):
    from learner import networks
    from learner.networks import block_dot

    monkeypatch.setattr(networks, "_BUILD_C", build_c)

    obs, actions = _batch(5)
    a, n = 4, 4
    x = agent_blocks(obs_history(obs, window)[:, :, 1:], actions[:, :, 1:], a, window)
    dense = reference_critic_inputs(
        reference_obs_history(obs, window)[:, :, 1:], actions[:, :, 1:], a
    )
    mlp = _mlp(2, dense.shape[-1], seed=2)
    first = mlp.layers[0]
    s = torch.randn(2, dense.shape[1], first.out_features)
    e, m, d = dense.shape
    w = first.weight.view(e, n, d // n, -1)  # agent i's block of rows
    contrib = torch.einsum("emnb,enbh->emnh", dense.view(e, m, n, d // n), w)
    with torch.no_grad():
        _close(block_dot(first, x, s), (contrib * s.unsqueeze(2)).sum(-1))


def test_critic_gradients_match_when_an_agent_never_sees_anything():
    obs, actions = _batch(7)
    obs[1, :, :, 3] = 0.0  # member 1's agent 3: no rows at all (an empty group)
    x = agent_blocks(obs_history(obs, 2)[:, :, :-1], actions[:, :, :-1], 4, 2)
    dense = reference_critic_inputs(reference_obs_history(obs, 2)[:, :, :-1], actions[:, :, :-1], 4)
    mlp = _mlp(2, dense.shape[-1], seed=3)
    grads = torch.autograd.grad(mlp(x).pow(2).sum(), list(mlp.parameters()))
    grads_ref = torch.autograd.grad(mlp(dense).pow(2).sum(), list(mlp.parameters()))
    for g, g_ref in zip(grads, grads_ref, strict=True):
        _close(g, g_ref)


def test_block_relevance_refuses_dense_values_after_the_critic_changed():
    obs, actions = _batch(6)
    x = agent_blocks(obs_history(obs, 2)[:, :, :-1], actions[:, :, :-1], 4, 2)
    mlp = _mlp(2, x.shape[-1])
    kept, _ = lrp_epsilon(mlp, x)
    before = kept.dense()  # computed while the weights are unchanged: kept as it is
    rel, _ = lrp_epsilon(mlp, x)
    with torch.no_grad():
        mlp.layers[0].weight.add_(1.0)  # an optimiser step, in place
    fresh, _ = lrp_epsilon(mlp, x)
    assert not torch.allclose(fresh.dense(), before)
    torch.testing.assert_close(kept.dense(), before)
    with pytest.raises(RuntimeError, match="changed after this relevance was computed"):
        rel.dense()


def test_the_dense_path_is_taken_when_hist_is_not_a_window_view():
    obs, actions = _batch()
    hist = reference_obs_history(obs, 3)[:, :, :-1]
    x = agent_blocks(hist, actions[:, :, :-1], 4, 3)
    assert type(x) is torch.Tensor
    torch.testing.assert_close(x, agent_blocks_dense(hist, actions[:, :, :-1], 4))


def test_lazy_inputs_are_read_only_and_otherwise_behave_as_dense():
    obs, actions = _batch()
    x = agent_blocks(obs_history(obs, 2)[:, :, :-1], actions[:, :, :-1], 4, 2)
    dense = x.dense()
    assert "AgentBlocks" in repr(x)
    blocks = x.view(2, -1, 4, x.block)
    torch.testing.assert_close(blocks[..., 0], dense.view(2, -1, 4, x.block)[..., 0])
    torch.testing.assert_close((x * 2).sum(), dense.sum() * 2)
    with pytest.raises(RuntimeError, match="read-only"):
        x.add_(1.0)
    x.clone().add_(1.0)  # a copy is an ordinary tensor


def _reference_learner(learner, monkeypatch) -> None:
    """Make `learner` (an RDNLearner) run the straightforward dense implementation."""
    import learner.batch as batch
    import learner.rdn as rdn

    monkeypatch.setattr(batch, "obs_history", reference_obs_history)
    monkeypatch.setattr(rdn, "agent_inputs", reference_agent_inputs)
    monkeypatch.setattr(rdn, "unroll", reference_unroll)
    monkeypatch.setattr(rdn, "lrp_epsilon", reference_lrp)
    a = learner.info.n_actions
    monkeypatch.setattr(
        learner, "critic_inputs", lambda hist, actions: reference_critic_inputs(hist, actions, a)
    )


@pytest.mark.parametrize(
    "rule", ["eps_residual", pytest.param("grad_x_input", marks=pytest.mark.slow)]
)
def test_rdn_updates_match_the_straightforward_implementation(rule, monkeypatch):
    """Two RDN learners from the same initialisation, one optimised and one running the dense
    reference, take the same two updates on random skirmish/3m episodes (2 seeds batched):
    their agent targets, metrics and parameters agree."""
    from actors.envs.registry import make_vec_env
    from cluster.bench.update import record_batch
    from learner.batch import TensorBatch
    from learner.rdn import RDNConfig, RDNLearner

    schema = make_vec_env("skirmish/3m", 1).info.schema()
    cfg = RDNConfig(lrp_rule=rule)
    torch.manual_seed(0)
    fast = RDNLearner(cfg, schema, n_ensemble=2)
    torch.manual_seed(0)
    slow = RDNLearner(cfg, schema, n_ensemble=2)
    batch = record_batch("skirmish/3m", 4, 2)
    tb = TensorBatch.from_episodes(batch)
    hist = obs_history(tb.obs, cfg.obs_window)[:, :, :-1]
    x_fast = fast.critic_inputs(hist, tb.actions)
    assert isinstance(x_fast, AgentBlocks)
    fast_metrics = [fast.step(batch) for _ in range(2)]
    targets_fast, q_fast = fast.agent_targets(x_fast)
    _reference_learner(slow, monkeypatch)
    slow_metrics = [slow.step(batch) for _ in range(2)]
    targets_slow, q_slow = slow.agent_targets(slow.critic_inputs(hist.contiguous(), tb.actions))
    _close(targets_fast, targets_slow, 1e-4)
    _close(q_fast, q_slow, 1e-4)
    _same_learners(fast, slow, fast_metrics, slow_metrics, rel=1e-3, atol=1e-5, scale=1e-4)


def _same_learners(
    one, two, metrics_one, metrics_two, rel: float, atol: float, scale: float
) -> None:
    """Two RDN learners' metrics of every update agree to `rel` (or `atol`) and their critics'
    and agents' parameters to `scale` (`_close`)."""
    for m1, m2 in zip(metrics_one, metrics_two, strict=True):
        assert m1.keys() == m2.keys()
        for k in m1:
            assert m1[k] == pytest.approx(m2[k], rel=rel, abs=atol), k
    for net in ("critic", "agent"):
        params = zip(getattr(one, net).parameters(), getattr(two, net).parameters(), strict=True)
        for p1, p2 in params:
            _close(p1, p2, scale)


def _tensor_batch(mask: torch.Tensor, n: int = 2, o: int = 3, a: int = 4):
    """A TensorBatch with the given mask [E, B, T] and distinct values everywhere else."""
    from learner.batch import TensorBatch

    e, b, t = mask.shape
    obs = torch.arange(e * b * (t + 1) * n * o, dtype=torch.float32).view(e, b, t + 1, n, o)
    return TensorBatch(
        obs=obs,
        state=torch.zeros(e, b, t + 1, 1),
        avail=torch.rand(e, b, t + 1, n, a) > 0.3,
        actions=torch.randint(0, a, (e, b, t, n)),
        reward=torch.randn(e, b, t),
        terminated=torch.zeros(e, b, t),
        mask=mask,
        policy_version=torch.zeros(e, b, dtype=torch.long),
    )


def test_real_steps_pack_each_members_real_steps_in_order():
    """`RealSteps` lays out each member's real steps first, in (episode, step) order, with
    the step after each (shift 1) alongside, and puts values back where they came from."""
    from learner.batch import RealSteps

    mask = torch.tensor(
        [[[1, 1, 1], [1, 0, 0]], [[0, 0, 0], [1, 1, 0]]], dtype=torch.float32
    )  # member 0: 4 real steps, member 1: 2 (its first episode is empty)
    tb = _tensor_batch(mask)
    steps = RealSteps(tb)
    assert steps.mask.tolist() == [[[1, 1, 1, 1]], [[1, 1, 0, 0]]]
    real = [[(0, 0), (0, 1), (0, 2), (1, 0)], [(1, 0), (1, 1)]]
    for shift in (0, 1):
        got = steps.take(tb.obs, shift)  # [E, 1, K, N, O]
        assert got.shape == (2, 1, 4, 2, 3)
        for k, pairs in enumerate(real):
            for j, (b, t) in enumerate(pairs):
                assert torch.equal(got[k, 0, j], tb.obs[k, b, t + shift])
    assert torch.equal(steps.take(tb.actions)[0, 0, 3], tb.actions[0, 1, 0])
    values = torch.randn(2, 2, 3, 5)
    assert torch.equal(steps.put(steps.take(values)), values * mask.unsqueeze(-1))
    hist = steps.hist(1)  # the critic's next observations, lazily
    assert torch.equal(hist.dense()[1, 0, 1], tb.obs[1, 1, 2])


@pytest.mark.parametrize(
    "overrides",
    [
        dict(critic_agent_encoder=16, agent_targets="counterfactual", td_lambda=0.8),
        dict(td_lambda=0.0, agent_targets="taken"),
        dict(agent_targets="counterfactual", split_actions="greedy", next_action="local_max"),
    ],
)
def test_rdn_on_the_real_steps_packed_matches_every_step(overrides):
    """With one observation per agent the critic side runs on the real steps packed
    (`RealSteps`): two learners from one initialisation, one packing them and one computing
    every step, take the same three updates on random skirmish/3m episodes of unequal lengths
    (2 seeds batched): their metrics and parameters agree."""
    from actors.envs.registry import make_vec_env
    from cluster.bench.update import record_batch
    from learner.batch import AllSteps, RealSteps, TensorBatch
    from learner.rdn import RDNConfig, RDNLearner

    schema = make_vec_env("skirmish/3m", 1).info.schema()
    cfg = RDNConfig(obs_window=1, agent_lr_scale=4.0, lr=1e-3, **overrides)
    torch.manual_seed(0)
    packed = RDNLearner(cfg, schema, n_ensemble=2)
    torch.manual_seed(0)
    full = RDNLearner(cfg, schema, n_ensemble=2)
    full.pack_steps = False
    batch = record_batch("skirmish/3m", 6, 2)
    tb = TensorBatch.from_episodes(batch)
    assert 0.2 < float(tb.mask.mean()) < 0.9  # a third or so of the steps are padding
    assert isinstance(packed.critic_steps(tb), RealSteps)
    assert isinstance(full.critic_steps(tb), AllSteps)
    metrics = [(packed.step(batch), full.step(batch)) for _ in range(3)]
    _same_learners(packed, full, *zip(*metrics, strict=True), rel=1e-4, atol=1e-6, scale=1e-5)


@pytest.mark.parametrize("recurrent", [True, False])
def test_unroll_of_agent_inputs_matches_the_dense_inputs(recurrent):
    obs, actions = _batch(4)
    a = 4
    x = agent_inputs(obs, actions[:, :, :-1], a)
    dense = reference_agent_inputs(obs, actions[:, :, :-1], a)
    assert isinstance(x, AgentInputs)
    torch.testing.assert_close(x, dense, rtol=0, atol=0)
    torch.manual_seed(0)
    agent = AgentNet(2, dense.shape[-1], a, hidden=8, fc=6, recurrent=recurrent)
    with torch.no_grad():
        for p in agent.parameters():
            p.normal_(0.0, 0.5)
    q, q_ref = unroll(agent, x), reference_unroll(agent, dense)
    _close(q, q_ref)
    grads = torch.autograd.grad(q.pow(2).sum(), list(agent.parameters()))
    grads_ref = torch.autograd.grad(q_ref.pow(2).sum(), list(agent.parameters()))
    for g, g_ref in zip(grads, grads_ref, strict=True):
        _close(g, g_ref)


def test_obs_norms_are_shared_until_the_observations_change():
    from learner.batch import obs_l1

    obs, _ = _batch()
    first = obs_l1(obs)
    assert obs_l1(obs) is first
    obs[0, 0, 0, 0, 0] += 1.0
    torch.testing.assert_close(obs_l1(obs), obs.abs().sum(-1))
