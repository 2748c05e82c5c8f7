"""TD targets and TD(lambda) returns against hand-computed values."""

import pytest
import torch

from learner.targets import lambda_returns, lambda_returns_scan, q_lambda_targets, td_targets

G = 0.9
# the step-by-step recursion (policy-gradient family) and the suffix scan (value family)
RETURNS = pytest.mark.parametrize("returns", [lambda_returns, lambda_returns_scan])


@pytest.mark.parametrize(
    "reward, terminated, next_value, expected",
    [
        ([1.0, 2.0], [0.0, 1.0], [10.0, 5.0], [1 + G * 10, 2.0]),  # terminal: no bootstrap
        ([0.0, 0.0], [0.0, 0.0], [3.0, 4.0], [G * 3, G * 4]),  # time-limit cut: bootstrap
        ([-1.0], [1.0], [100.0], [-1.0]),
    ],
)
def test_td_targets(reward, terminated, next_value, expected):
    y = td_targets(torch.tensor(reward), torch.tensor(terminated), torch.tensor(next_value), G)
    torch.testing.assert_close(y, torch.tensor(expected))


def _lam(reward, terminated, mask, values, lam, returns=lambda_returns):
    args = [torch.tensor([x]) for x in (reward, terminated, mask, values)]
    return returns(*args, gamma=G, lam=lam)[0].tolist()


@RETURNS
def test_lambda_returns_terminal_episode(returns):
    r, term, mask, v = [1.0, 2.0, 3.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0], [0.5, 0.6, 0.7, 9.0]
    # lambda = 1: Monte-Carlo returns; the value after the terminal step is ignored.
    g2 = 3.0
    g1 = 2.0 + G * g2
    g0 = 1.0 + G * g1
    assert _lam(r, term, mask, v, 1.0, returns) == pytest.approx([g0, g1, g2])
    # lambda = 0: one-step TD targets.
    assert _lam(r, term, mask, v, 0.0, returns) == pytest.approx([1 + G * 0.6, 2 + G * 0.7, 3.0])
    # lambda = 0.5 by hand.
    h2 = 3.0
    h1 = 2.0 + G * (0.5 * 0.7 + 0.5 * h2)
    h0 = 1.0 + G * (0.5 * 0.6 + 0.5 * h1)
    assert _lam(r, term, mask, v, 0.5, returns) == pytest.approx([h0, h1, h2])


@RETURNS
def test_lambda_returns_time_limit_cut_and_padding(returns):
    # Two real steps then padding; the episode was cut (not terminal): bootstrap from V[2].
    r, term, mask, v = [1.0, 1.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 4.0, 99.0]
    g1 = 1.0 + G * 4.0
    g0 = 1.0 + G * (0.2 * 0.0 + 0.8 * g1)
    assert _lam(r, term, mask, v, 0.8, returns) == pytest.approx([g0, g1, 0.0])


def test_q_lambda_targets_zero_is_one_step_td_and_one_is_the_return():
    r = torch.tensor([[1.0, 2.0, 3.0]])
    term = torch.tensor([[0.0, 0.0, 1.0]])
    mask = torch.ones(1, 3)
    nxt = torch.tensor([[10.0, 20.0, 30.0]])  # values of the states after each step
    torch.testing.assert_close(
        q_lambda_targets(r, term, mask, nxt, G, 0.0), td_targets(r, term, nxt, G)
    )
    # λ = 1 on a terminated episode: the discounted Monte Carlo returns, no value used.
    expected = [1 + G * 2 + G * G * 3, 2 + G * 3, 3.0]
    torch.testing.assert_close(
        q_lambda_targets(r, term, mask, nxt, G, 1.0), torch.tensor([expected])
    )
    # λ = 0.5 by hand: G2 = 3, G1 = 2 + G (0.5 * 20 + 0.5 * G2), G0 = 1 + G (0.5 * 10 + 0.5 G1)
    g1 = 2 + G * (0.5 * 20 + 0.5 * 3)
    g0 = 1 + G * (0.5 * 10 + 0.5 * g1)
    torch.testing.assert_close(
        q_lambda_targets(r, term, mask, nxt, G, 0.5), torch.tensor([[g0, g1, 3.0]])
    )


def _lambda_returns_by_definition(reward, terminated, mask, values, gamma, lam):
    """The recursion of the docstring, one episode and one step at a time."""
    out = torch.zeros_like(reward)
    flat = [x.reshape(-1, x.shape[-1]) for x in (reward, terminated, mask, values)]
    res = out.view(-1, reward.shape[-1])
    for i, (r, term, m, v) in enumerate(zip(*flat, strict=True)):
        n = int(m.sum())
        g = 0.0
        for t in range(n - 1, -1, -1):
            last = t == n - 1
            blend = v[t + 1] if last else (1 - lam) * v[t + 1] + lam * g
            g = r[t] + gamma * (1 - term[t]) * blend
            res[i, t] = g
    return out


@RETURNS
@pytest.mark.parametrize("t", [1, 2, 9, 64, 121])
@pytest.mark.parametrize("lam", [0.0, 0.6, 0.8, 1.0])
def test_lambda_returns_match_the_definition_on_random_padded_batches(lam, t, returns):
    gen = torch.Generator().manual_seed(t)
    e, b = 2, 5
    lengths = torch.randint(1, t + 1, (e, b), generator=gen)
    mask = (torch.arange(t) < lengths.unsqueeze(-1)).float()
    terminated = torch.zeros(e, b, t)
    ends = torch.rand(e, b, generator=gen) < 0.5  # the others were cut by the time limit
    terminated.scatter_(-1, (lengths - 1).unsqueeze(-1), ends.float().unsqueeze(-1))
    reward = torch.randn(e, b, t, generator=gen) * mask
    values = torch.randn(e, b, t + 1, generator=gen)
    torch.testing.assert_close(
        returns(reward, terminated, mask, values, G, lam),
        _lambda_returns_by_definition(reward, terminated, mask, values, G, lam),
    )


def test_scan_matches_the_recursion_with_padding_inside_and_leading_axes():
    """Masks with holes (a real step after padding) and an agent axis: both forms agree."""
    gen = torch.Generator().manual_seed(1)
    shape = (3, 4, 2, 30)
    mask = (torch.rand(shape, generator=gen) < 0.8).float()
    terminated = (torch.rand(shape, generator=gen) < 0.1).float()
    reward = torch.randn(shape, generator=gen)
    values = torch.randn((*shape[:-1], shape[-1] + 1), generator=gen)
    torch.testing.assert_close(
        lambda_returns_scan(reward, terminated, mask, values, G, 0.8),
        lambda_returns(reward, terminated, mask, values, G, 0.8),
    )
