"""Returns and temporal-difference targets as pure functions on [.., T] tensors.

`terminated[t]` is 1 when the environment ended at transition t (not a time-limit cut), so
bootstrapping stops there; `mask[t]` is 1 on real transitions and 0 on padding.
"""

from __future__ import annotations

import torch


def td_targets(
    reward: torch.Tensor, terminated: torch.Tensor, next_value: torch.Tensor, gamma: float
) -> torch.Tensor:
    """One-step targets y_t = r_t + γ (1 - terminated_t) V(s_{t+1}).

    Shapes: reward, terminated, next_value [..., T] (or with a trailing agent axis, broadcast).
    """
    return reward + gamma * (1.0 - terminated) * next_value


def lambda_returns(
    reward: torch.Tensor,
    terminated: torch.Tensor,
    mask: torch.Tensor,
    values: torch.Tensor,
    gamma: float,
    lam: float,
) -> torch.Tensor:
    """TD(λ) returns G^λ_t, computed backwards.

    G_t = r_t + γ (1 - term_t) [(1 - λ) V_{t+1} + λ G_{t+1}], and at the last real step of an
    episode that was cut by the time limit G_t = r_t + γ V_{t+1} (bootstrap).

    Args:
        reward, terminated, mask: [..., T].
        values: [..., T+1] value estimates of every state including the one after step T-1.
        gamma, lam: discount and λ.
    Returns:
        [..., T]; padded steps hold 0.
    """
    t_len = reward.shape[-1]
    out = torch.zeros_like(reward)
    # The per-step recursion below does exactly the arithmetic of
    #   blend = nxt ((1 - λ) V_{t+1} + λ G_{t+1}) + (1 - nxt) V_{t+1}
    #   G_t = r_t + γ (1 - term_t) blend
    # (nxt: step t+1 is real), with everything that does not depend on G_{t+1} computed for
    # all steps at once; results are bit for bit those of the step-by-step form.
    v_next = values[..., 1:]
    nxt_real = torch.cat([mask[..., 1:], torch.zeros_like(mask[..., :1])], dim=-1)
    kept = (1.0 - lam) * v_next
    bootstrap = (1.0 - nxt_real) * v_next
    discount = gamma * (1.0 - terminated)
    # At a padded step the "next return" is the bootstrap value itself, so the last real step
    # of a cut episode reduces to r + γ V_{t+1}.
    g_next = values[..., t_len]
    for t in range(t_len - 1, -1, -1):
        blend = nxt_real[..., t] * (kept[..., t] + lam * g_next) + bootstrap[..., t]
        g = reward[..., t] + discount[..., t] * blend
        out[..., t] = g * mask[..., t]
        g_next = torch.where(mask[..., t] > 0, g, g_next)
    return out


def q_lambda_targets(
    reward: torch.Tensor,
    terminated: torch.Tensor,
    mask: torch.Tensor,
    next_value: torch.Tensor,
    gamma: float,
    lam: float,
) -> torch.Tensor:
    """Q(λ) targets from the next states' target values: one-step TD when λ = 0, else the
    λ-return over them (`lambda_returns`, as PyMARL2's TD(λ) QMIX builds it).

    Shapes: reward, terminated, mask, next_value [..., T] -> [..., T] (padded steps: 0 when
    λ > 0, unmasked one-step values when λ = 0; losses mask them either way).
    """
    if lam == 0.0:
        return td_targets(reward, terminated, next_value, gamma)
    values = torch.cat([torch.zeros_like(next_value[..., :1]), next_value], dim=-1)
    return lambda_returns(reward, terminated, mask, values, gamma, lam)
