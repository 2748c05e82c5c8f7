"""Pieces every learner composes: configs shared by the agent network, the optimiser step with
per-member clipping and a NaN guard, and target-network bookkeeping."""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import nn

from learner.networks import VersionedWeights, clip_grad_norm_per_member


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


class AgentCriticLearner:
    """Weights and checkpoints of a learner with a shared agent network, a critic with a target
    copy, and one Updater for each (RDN, the CAC family, COMA).

    Subclasses set `agent`, `critic`, `target_critic` (a TargetNet), `agent_updater`,
    `critic_updater` and `updates`, and list any further modules in `extra_modules()`.
    """

    agent: nn.Module
    critic: nn.Module
    target_critic: TargetNet
    agent_updater: Updater
    critic_updater: Updater
    updates: int

    def extra_modules(self) -> dict[str, nn.Module | None]:
        """Checkpointed modules beyond the common ones (None: absent in this variant)."""
        return {}

    def get_weights(self) -> VersionedWeights:
        return VersionedWeights.from_module(self.agent, self.updates)

    def state_dict(self) -> dict:
        extra = {
            k: m.state_dict() if m is not None else None for k, m in self.extra_modules().items()
        }
        return {
            "agent": self.agent.state_dict(),
            "critic": self.critic.state_dict(),
            "target_critic": self.target_critic.module.state_dict(),
            "agent_optimiser": self.agent_updater.optimiser.state_dict(),
            "critic_optimiser": self.critic_updater.optimiser.state_dict(),
            "updates": self.updates,
            **extra,
        }

    def load_state_dict(self, state: dict) -> None:
        self.agent.load_state_dict(state["agent"])
        self.critic.load_state_dict(state["critic"])
        self.target_critic.module.load_state_dict(state["target_critic"])
        for key, module in self.extra_modules().items():
            if module is not None:
                module.load_state_dict(state[key])
        self.agent_updater.optimiser.load_state_dict(state["agent_optimiser"])
        self.critic_updater.optimiser.load_state_dict(state["critic_optimiser"])
        self.updates = int(state["updates"])
