"""Pieces every learner composes: configs shared by the agent network, the optimiser step with
per-member clipping and a NaN guard, and target-network bookkeeping."""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import nn

from learner.networks import clip_grad_norm_per_member


class NonFiniteLossError(FloatingPointError):
    """A loss became NaN or inf; training must stop before the optimiser applies it."""


@dataclass(frozen=True)
class AgentConfig:
    """The shared agent network (seed 5.3.3: GRU 64 -> FC 32 -> FC 32 -> actions).

    Attributes:
        hidden: GRU hidden size.
        fc: width of the two fully connected layers after the GRU.
    """

    hidden: int = 64
    fc: int = 32

    def validate(self) -> None:
        if self.hidden < 1 or self.fc < 1:
            raise ValueError("agent.hidden and agent.fc must be >= 1")


class Updater:
    """Adam over a parameter group, per-member gradient clipping, and a NaN/inf guard."""

    def __init__(self, params: list[nn.Parameter], lr: float, grad_norm_clip: float, name: str):
        self.params = list(params)
        self.name = name
        self.grad_norm_clip = grad_norm_clip
        self.optimiser = torch.optim.Adam(self.params, lr=lr, foreach=True)

    def apply(self, loss_per_member: torch.Tensor) -> torch.Tensor:
        """Backpropagate the sum of per-member losses [E] and step; returns grad norms [E]."""
        if not torch.isfinite(loss_per_member).all():
            bad = loss_per_member.detach().cpu().tolist()
            raise NonFiniteLossError(f"{self.name} loss is not finite: {bad}; update not applied")
        self.optimiser.zero_grad(set_to_none=True)
        loss_per_member.sum().backward()
        norms = clip_grad_norm_per_member(self.params, self.grad_norm_clip)
        self.optimiser.step()
        return norms


class TargetNet:
    """A frozen copy of a module, refreshed by hard copy every `interval` updates."""

    def __init__(self, module: nn.Module, interval: int):
        self.source = module
        self.interval = interval
        self.module = copy.deepcopy(module)
        self.module.requires_grad_(False)

    def maybe_update(self, updates: int) -> bool:
        if updates % self.interval == 0:
            self.module.load_state_dict(self.source.state_dict())
            return True
        return False
