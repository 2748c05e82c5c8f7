"""EM-CAC's KL mask (seed chapter 4, Algorithm 2 line 19) and the Polyak-averaged target policy.

A target policy θ̃^π is kept as a Polyak (exponential) average of every past policy. On every
timestep of the training batch both policies are evaluated on the same agent history and the
KL divergence KL(π_θ || π_θ̃) is taken; where it exceeds the threshold K the policy-gradient
advantage is set to zero, so data on which the current policy has already moved far from the
average policy no longer pushes it further (seed: A_t = G_t - V_t where KL(θ^π || θ̃^π) < K).

Direction: KL(current || target) = Σ_u π(u) [log π(u) - log π̃(u)], the dissertation's notation. The
expectation is under the policy being trained, so it grows when the current policy puts its
mass on actions the average policy considers unlikely (the "moved too far" case) and it stays
finite because a softmax target has full support on the available actions.

Rate and threshold (the dissertation gives neither): τ = 0.05 and K = 0.05 by default. The target's
mean age is (1 - τ) / τ ≈ 19 updates, two to three lifetimes of an episode in the cycling buffer
(32 episodes, 4 new per step: 8 updates), so π̃ averages the policies that produced the data
being reused plus a little history, and KL(π || π̃) measures drift on the timescale of reuse.
Measured with the mask off on skirmish/3m (3 seeds, E-CAC data flow, plain advantages, before
advantage normalisation became the default): with τ = 0.05 the KL's 90th percentile was 0.06
during the fast early learning (~10k steps) and 0.005-0.02 later, with a 99th percentile of
0.03-0.25, so K = 0.05 trims about a tenth of the steps early on and only the tail
afterwards. τ = 0.01 (a ~100-update average) lagged so far behind early learning that the
KL's median was 0.26 at 10k steps; with K = 0.02 it masked 54% of the steps and stalled the
actors (measured, not kept). With normalised advantages the mask dropped 0.6-27% of the
timesteps on 3m and 0-25% on 2s3z and 3s5z (the masked fraction at each evaluation in
results/pg/3m and results/pg/protoss).

All functions are pure and work on any leading shape [...] with a trailing action axis A.
"""

from __future__ import annotations

import torch
from torch import nn


def categorical_kl(logp: torch.Tensor, logq: torch.Tensor, avail: torch.Tensor) -> torch.Tensor:
    """KL(p || q) of two categorical distributions over the available actions.

    Args:
        logp: log-probabilities of p (the current policy).
        logq: log-probabilities of q (the target policy).
        avail: available actions (bool); unavailable actions contribute nothing.
    Returns:
        KL per distribution, >= 0 up to rounding.
    Shapes:
        logp, logq, avail [..., A] -> [...].
    """
    terms = logp.exp() * (logp - logq)
    return torch.where(avail, terms, torch.zeros_like(terms)).sum(-1).clamp_min(0.0)


def kl_keep_mask(kl: torch.Tensor, threshold: float) -> torch.Tensor:
    """1.0 where the KL is within the threshold (advantage kept), 0.0 where it exceeds it.

    Shapes: kl [...] -> [...] float.
    """
    return (kl <= threshold).to(kl.dtype)


def joint_kl(kl: torch.Tensor) -> torch.Tensor:
    """KL of the joint policy from per-agent KLs [..., N] -> [..., N] (every agent gets the sum).

    Agents act independently given their own histories, so the joint policy factorises and
    its KL is the sum of the agents' KLs; broadcasting it back masks whole timesteps.
    """
    return kl.sum(-1, keepdim=True).expand_as(kl)


def masked_advantages(advantages: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """Zero the advantage wherever the mask drops a timestep; nothing else changes.

    Shapes: advantages and keep broadcastable, e.g. [E, B, T, 1] and [E, B, T, N].
    """
    return advantages * keep


def masked_fraction(keep: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Fraction of real entries the KL mask dropped, per ensemble member.

    Args:
        keep: [E, ...] 1 where kept.
        mask: [E, ...] 1 on real (non-padding) entries.
    Returns:
        [E].
    """
    dims = tuple(range(1, keep.dim()))
    return ((1.0 - keep) * mask).sum(dims) / mask.sum(dims).clamp_min(1.0)


@torch.no_grad()
def polyak_update_(target: nn.Module, source: nn.Module, tau: float) -> None:
    """θ̃ <- (1 - τ) θ̃ + τ θ for every parameter (in place).

    With τ = 1 this is a hard copy; with small τ the target is an exponentially weighted
    average of all past source parameters with an effective horizon of about 1/τ updates.
    """
    for t, s in zip(target.parameters(), source.parameters(), strict=True):
        t.lerp_(s, tau)
