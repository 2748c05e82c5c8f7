"""Acting: exploration schedules and action selection from the agent network's outputs."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class ExplorationConfig:
    """ε-greedy schedule for the value family (the dissertation, 5.3.3: 1.0 -> 0.05 over 50k
    steps on SMAC, 2000 steps on the matrix games); policy-gradient agents sample their softmax
    instead.

    Attributes:
        epsilon_start: ε at t_env = 0.
        epsilon_finish: ε after the anneal.
        epsilon_anneal_time: env steps of linear annealing.
    """

    epsilon_start: float = 1.0
    epsilon_finish: float = 0.05
    epsilon_anneal_time: int = 50_000

    def validate(self) -> None:
        for name in ("epsilon_start", "epsilon_finish"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        if self.epsilon_anneal_time < 1:
            raise ValueError(f"epsilon_anneal_time must be >= 1, got {self.epsilon_anneal_time}")

    def epsilon(self, t_env: int) -> float:
        frac = min(1.0, t_env / self.epsilon_anneal_time)
        return self.epsilon_start + frac * (self.epsilon_finish - self.epsilon_start)


def select_actions(
    out: torch.Tensor,
    avail: torch.Tensor,
    kind: str,
    epsilon: float,
    greedy: bool,
    gen: torch.Generator,
) -> torch.Tensor:
    """Pick one available action per agent.

    Args:
        out: network outputs [..., A] (Q-values for kind "q", logits for "softmax").
        avail: available actions [..., A] bool; every row has at least one.
        kind: "q" (ε-greedy) or "softmax" (sample the masked policy).
        epsilon: exploration rate for "q".
        greedy: act greedily (evaluation) whatever the kind.
        gen: random generator (for reproducible acting).
    Returns:
        actions [...] long, each available.
    """
    masked = out.masked_fill(~avail, float("-inf"))
    best = masked.argmax(-1)
    if greedy:
        return best
    if kind == "softmax":
        probs = torch.softmax(masked, -1).reshape(-1, out.shape[-1])
        return torch.multinomial(probs, 1, generator=gen).view(best.shape)
    flat_avail = avail.reshape(-1, avail.shape[-1]).float()
    random = torch.multinomial(flat_avail, 1, generator=gen).view(best.shape)
    explore = torch.rand(best.shape, generator=gen) < epsilon
    return torch.where(explore, random, best)
