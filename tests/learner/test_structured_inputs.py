"""The structured network inputs (the agents' `AgentInputs`, RDN's `ObsWindows` and
`AgentBlocks`, `block_preactivation`, LRP's per-agent sums by `block_dot`) compute what the
straightforward dense implementation computes: the agents' inputs by concatenation and the
step-by-step unroll (kept here), the critic's windows and input as `learner.rdn_reference`
builds them."""

import pytest
import torch
from torch.nn import functional as F

from learner.batch import AgentInputs, agent_inputs
from learner.critic_inputs import AgentBlocks, ObsWindows, agent_blocks, obs_history
from learner.networks import MLP, AgentBlockLinear, AgentNet, unroll
from learner.rdn_fast import agent_targets
from learner.rdn_reference import critic_inputs as reference_critic_inputs
from learner.rdn_reference import lrp_shares
from learner.rdn_reference import obs_windows as reference_obs_history


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


def _close(got: torch.Tensor, want: torch.Tensor, scale: float = 1e-5) -> None:
    """float32 agreement up to summation order (the tolerance follows the values' size)."""
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
def test_obs_history_holds_the_concatenated_windows_and_slices_stay_windows(window):
    obs, _ = _batch()
    hist = obs_history(obs, window)
    ref = reference_obs_history(obs, window)
    assert isinstance(hist, ObsWindows) and hist.shape == ref.shape
    torch.testing.assert_close(hist.dense(), ref, rtol=0, atol=0)
    for sl in (slice(None, -1), slice(1, None), slice(2, 5), slice(-3, None)):
        part = hist[:, :, sl]
        assert isinstance(part, ObsWindows) and part.shape == ref[:, :, sl].shape
        torch.testing.assert_close(part.dense(), ref[:, :, sl], rtol=0, atol=0)
        twice = part[:, :, 1:].dense()
        torch.testing.assert_close(twice, ref[:, :, sl][:, :, 1:], rtol=0, atol=0)
    with pytest.raises(IndexError, match="lo:hi"):
        hist[0]


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


@pytest.mark.parametrize("window", [1, 4])
def test_the_shares_of_agent_blocks_are_the_references_on_the_dense_input(window):
    obs, actions = _batch(3)
    a, n = 4, 4
    hist = obs_history(obs, window)[:, :, :-1]
    x = agent_blocks(hist, actions[:, :, :-1], a, window)
    dense = reference_critic_inputs(hist.dense(), actions[:, :, :-1], a)
    mlp = _mlp(2, dense.shape[-1], seed=1)
    got = agent_targets(mlp, x, actions[:, :, :-1].reshape(2, -1, n), None, 0.01, window * 5)
    shares, q = lrp_shares(mlp, dense, n, 0.01)
    _close(got.q, q)
    _close(got.shares, shares)
    _close(got.shares.sum(-1), q)  # conserves


@pytest.mark.parametrize("build_c", [0.0, float("inf")])  # c summed / s gathered per pair
@pytest.mark.parametrize("window", [1, 4])
def test_block_dot_is_each_agents_dense_contribution_dotted_with_s(window, build_c, monkeypatch):
    from learner import critic_layer
    from learner.critic_layer import block_dot

    monkeypatch.setattr(critic_layer, "_BUILD_C", build_c)

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


def test_the_dense_path_is_taken_when_hist_is_not_a_window_view():
    obs, actions = _batch()
    hist = reference_obs_history(obs, 3)[:, :, :-1]
    x = agent_blocks(hist, actions[:, :, :-1], 4, 3)
    assert type(x) is torch.Tensor
    torch.testing.assert_close(x, reference_critic_inputs(hist, actions[:, :, :-1], 4))


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
    from learner.critic_inputs import RealSteps

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
    hist = steps.hist(1)  # the critic's next observations, as windows
    assert torch.equal(hist.dense()[1, 0, 1], tb.obs[1, 1, 2])


@pytest.mark.parametrize("recurrent", [True, False])
def test_unroll_of_agent_inputs_matches_the_dense_inputs(recurrent):
    obs, actions = _batch(4)
    a = 4
    x = agent_inputs(obs, actions[:, :, :-1], a)
    dense = reference_agent_inputs(obs, actions[:, :, :-1], a)
    assert isinstance(x, AgentInputs) and x.shape == dense.shape
    torch.testing.assert_close(x.dense(), dense, rtol=0, atol=0)
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
