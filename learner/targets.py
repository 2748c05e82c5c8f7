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


def lambda_returns_scan(
    reward: torch.Tensor,
    terminated: torch.Tensor,
    mask: torch.Tensor,
    values: torch.Tensor,
    gamma: float,
    lam: float,
) -> torch.Tensor:
    """The returns of `lambda_returns` (arguments and shapes as there; equal up to float
    rounding) in ceil(log2 T) vector steps instead of T.

    With c_t = r_t + γ (1 - term_t) [nxt_t (1 - λ) V_{t+1} + (1 - nxt_t) V_{t+1}] and
    β_t = γ (1 - term_t) nxt_t λ (nxt_t: step t+1 is real), G_t = c_t + β_t g_{t+1}, where
    g_t, the latest real return at or after t, is affine in g_{t+1}:
    g_t = m_t c_t + (m_t β_t + 1 - m_t) g_{t+1}, g_T = V_T. The composition of those affine
    maps from every t to the end is a suffix scan (Hillis-Steele doubling). The value family's
    Q(λ) targets use it (`q_lambda_targets`: 4-15x cheaper than the per-step loop at T = 27-120);
    the policy-gradient family keeps `lambda_returns`, so its committed runs replay bit for bit.
    """
    t_len = reward.shape[-1]
    v_next, v_end = values[..., 1:], values[..., t_len:]
    nxt_real = torch.cat([mask[..., 1:], torch.zeros_like(mask[..., :1])], dim=-1)
    discount = gamma * (1.0 - terminated)
    c = reward + discount * v_next * (1.0 - lam * nxt_real)
    beta = discount * nxt_real * lam
    alpha, slope = mask * c, mask * beta + (1.0 - mask)
    shift = 1
    while shift < t_len:  # (α, b)_t <- (α, b)_t composed with (α, b)_{t+shift}
        alpha = torch.cat(
            [alpha[..., :-shift] + slope[..., :-shift] * alpha[..., shift:], alpha[..., -shift:]],
            dim=-1,
        )
        slope = torch.cat([slope[..., :-shift] * slope[..., shift:], slope[..., -shift:]], dim=-1)
        shift *= 2
    g = alpha + slope * v_end  # g_t, t = 0 .. T-1
    g_after = torch.cat([g[..., 1:], v_end], dim=-1)
    return (c + beta * g_after) * mask


def q_lambda_targets(
    reward: torch.Tensor,
    terminated: torch.Tensor,
    mask: torch.Tensor,
    next_value: torch.Tensor,
    gamma: float,
    lam: float,
) -> torch.Tensor:
    """Q(λ) targets from the next states' target values: one-step TD when λ = 0, else the
    λ-return over them (`lambda_returns_scan`, as PyMARL2's TD(λ) QMIX builds it).

    Shapes: reward, terminated, mask, next_value [..., T] -> [..., T] (padded steps: 0 when
    λ > 0, unmasked one-step values when λ = 0; losses mask them either way).
    """
    if lam == 0.0:
        return td_targets(reward, terminated, next_value, gamma)
    values = torch.cat([torch.zeros_like(next_value[..., :1]), next_value], dim=-1)
    return lambda_returns_scan(reward, terminated, mask, values, gamma, lam)
