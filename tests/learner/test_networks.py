"""Multi-agent and ensemble properties of the networks."""

import torch

from learner.networks import AgentNet, QMixer, clip_grad_norm_per_member, unroll


def test_agent_output_depends_only_on_its_own_inputs():
    """Decentralised execution: agent i's Q-values ignore agent j's inputs."""
    torch.manual_seed(0)
    net = AgentNet(1, input_dim=7, n_actions=4)
    x = torch.randn(1, 1, 5, 3, 7)  # [E, B, T, N, D]
    base = unroll(net, x)
    x2 = x.clone()
    x2[..., 2, :] = torch.randn(1, 1, 5, 7)  # change agent 2 only, at every step
    out = unroll(net, x2)
    torch.testing.assert_close(out[..., :2, :], base[..., :2, :])
    assert not torch.allclose(out[..., 2, :], base[..., 2, :])


def test_recurrence_carries_information_forward():
    torch.manual_seed(0)
    net = AgentNet(1, input_dim=4, n_actions=3)
    x = torch.randn(1, 2, 4, 1, 4)
    x2 = x.clone()
    x2[:, :, 0] += 1.0  # change only the first step
    a, b = unroll(net, x), unroll(net, x2)
    assert not torch.allclose(a[:, :, 3], b[:, :, 3])


def test_ensemble_members_do_not_interact():
    torch.manual_seed(0)
    net = AgentNet(3, input_dim=5, n_actions=2)
    x = torch.randn(3, 2, 4, 2, 5)
    base = unroll(net, x)
    with torch.no_grad():
        net.fc1.weight[2].mul_(-3.0)
    out = unroll(net, x)
    torch.testing.assert_close(out[:2], base[:2])
    assert not torch.allclose(out[2], base[2])


def test_qmixer_is_monotonic_in_every_agent_q():
    torch.manual_seed(0)
    mixer = QMixer(2, n_agents=3, cond_dim=6)
    qs = torch.randn(2, 10, 3, requires_grad=True)
    cond = torch.randn(2, 10, 6)
    (grad,) = torch.autograd.grad(mixer(qs, cond).sum(), qs)
    assert torch.all(grad >= 0)


def test_qmixer_computes_the_qmix_formula_row_by_row():
    """Q_tot = elu(q . |W1(s)| + b1(s)) . |W2(s)| + V(s), one row at a time with plain
    matrix products, for each member's own hypernetworks."""
    torch.manual_seed(0)
    mixer = QMixer(2, n_agents=3, cond_dim=6, embed=4, hyper_hidden=5)
    qs, cond = torch.randn(2, 7, 3), torch.randn(2, 7, 6)
    out = mixer(qs, cond)
    for e in range(2):
        for m in range(7):
            s = cond[e : e + 1, m : m + 1]
            w1 = mixer.hyper_w1(s.expand(2, 1, 6))[e, 0].abs().view(3, 4)
            b1 = mixer.hyper_b1(s.expand(2, 1, 6))[e, 0]
            w2 = mixer.hyper_w2(s.expand(2, 1, 6))[e, 0].abs()
            v = mixer.value(s.expand(2, 1, 6))[e, 0]
            expected = torch.nn.functional.elu(qs[e, m] @ w1 + b1) @ w2 + v
            torch.testing.assert_close(out[e, m], expected)


def test_clip_grad_norm_per_member_clips_each_member_by_its_own_norm():
    p = torch.nn.Parameter(torch.zeros(2, 3))
    p.grad = torch.tensor([[3.0, 4.0, 0.0], [0.3, 0.4, 0.0]])  # norms 5 and 0.5
    norms = clip_grad_norm_per_member([p], max_norm=1.0)
    torch.testing.assert_close(norms, torch.tensor([5.0, 0.5]))
    torch.testing.assert_close(p.grad[0].norm(), torch.tensor(1.0), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(p.grad[1], torch.tensor([0.3, 0.4, 0.0]))  # under the limit


def test_unroll_matches_the_agent_called_step_by_step():
    """The batched unroll (input projection and head over every step at once) computes what
    the actors compute calling the agent one step at a time."""
    torch.manual_seed(0)
    net = AgentNet(2, input_dim=5, n_actions=3)
    x = torch.randn(2, 4, 6, 3, 5)  # [E, B, T, N, D]
    h = net.init_hidden(2, 4 * 3)
    steps = []
    for t in range(6):
        out, h = net(x[:, :, t].reshape(2, 12, 5), h)
        steps.append(out.view(2, 4, 3, 3))
    torch.testing.assert_close(unroll(net, x), torch.stack(steps, dim=2))
