"""Pieces every learner composes: configs shared by the agent network, the optimiser step with
per-member clipping and a NaN guard, and target-network bookkeeping."""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import nn

from buffer_service.episode import EpisodeSchema
from learner.batch import AgentInputLayout
from learner.networks import ActingSpec, AgentNet, VersionedWeights, clip_grad_norm_per_member
from learner.timers import timed

OPTIMISERS = ("adam", "rmsprop")


class NonFiniteLossError(FloatingPointError):
    """A loss became NaN or inf; training must stop before the optimiser applies it."""


@dataclass(frozen=True)
class AgentConfig:
    """The shared agent network (seed 5.3.3: GRU 64 -> FC 32 -> FC 32 -> actions).

    Attributes:
        hidden: GRU hidden size (width of the first layer when not recurrent).
        fc: width of the two fully connected layers after it.
        recurrent: a GRU first layer (DRQN, the dissertation's) or a feed-forward one (PyMARL-family
            codebases' `use_rnn: False`; every step of a batch in one call, so much cheaper).
    """

    hidden: int = 64
    fc: int = 32
    recurrent: bool = True

    def validate(self) -> None:
        if self.hidden < 1 or self.fc < 1:
            raise ValueError("agent.hidden and agent.fc must be >= 1")

    def acting_spec(self, schema: EpisodeSchema, policy_kind: str) -> ActingSpec:
        """The acting network's description for `schema` (input: `AgentInputLayout`).

        Args:
            schema: the env's episode sizes.
            policy_kind: "q" or "softmax" (the learner's family).
        Returns:
            An ActingSpec that rollout workers build their network from.
        """
        layout = AgentInputLayout(schema.obs_dim, schema.n_actions, schema.n_agents)
        return ActingSpec(layout, self.hidden, self.fc, self.recurrent, policy_kind)

    def build(self, n_ensemble: int, schema: EpisodeSchema) -> AgentNet:
        """The agent network for `schema` (`acting_spec(...).build`)."""
        return self.acting_spec(schema, "q").build(n_ensemble)


def validate_optimiser(name: str) -> None:
    if name not in OPTIMISERS:
        raise ValueError(f"optimiser {name!r} is not one of {OPTIMISERS}")


def validate_value_schedule(
    gamma: float,
    lr: float,
    grad_norm_clip: float,
    target_update_episodes: int,
    optimiser: str,
    reward_norm: str,
    td_lambda: float,
) -> None:
    """The checks every Q-learning config (IQL, VDN, QMIX, QMIX-nostate, RDN) shares."""
    if not 0.0 <= gamma <= 1.0:
        raise ValueError(f"gamma must be in [0, 1], got {gamma}")
    if lr <= 0:
        raise ValueError(f"lr must be > 0, got {lr}")
    if grad_norm_clip <= 0:
        raise ValueError(f"grad_norm_clip must be > 0, got {grad_norm_clip}")
    if target_update_episodes < 1:
        raise ValueError(f"target_update_episodes must be >= 1, got {target_update_episodes}")
    validate_optimiser(optimiser)
    if reward_norm not in REWARD_NORMS:
        raise ValueError(f"reward_norm {reward_norm!r} is not one of {REWARD_NORMS}")
    if not 0.0 <= td_lambda <= 1.0:
        raise ValueError(f"td_lambda must be in [0, 1], got {td_lambda}")


class Updater:
    """Adam (or RMSprop) over a parameter group, per-member gradient clipping, and a NaN/inf
    guard. RMSprop uses PyMARL's α = 0.99, ε = 1e-5."""

    def __init__(
        self,
        params: list[nn.Parameter],
        lr: float,
        grad_norm_clip: float,
        name: str,
        optimiser: str = "adam",
    ):
        validate_optimiser(optimiser)
        self.params = list(params)
        self.name = name
        self.grad_norm_clip = grad_norm_clip
        if optimiser == "adam":
            self.optimiser = torch.optim.Adam(self.params, lr=lr, foreach=True)
        else:
            self.optimiser = torch.optim.RMSprop(
                self.params, lr=lr, alpha=0.99, eps=1e-5, foreach=True
            )

    def apply(self, loss_per_member: torch.Tensor) -> torch.Tensor:
        """Backpropagate the sum of per-member losses [E] and step; returns grad norms [E]."""
        self.zero_grad()
        self.backward(loss_per_member)
        return self.step()

    def zero_grad(self) -> None:
        """Start an update whose loss comes in parts (`backward` each, then `step`)."""
        self.optimiser.zero_grad(set_to_none=True)

    def backward(self, loss_per_member: torch.Tensor) -> None:
        """Add the gradient of the sum of per-member losses [E] (a whole loss, or one pass's
        part of it: `learner.passes`) to the parameters' gradients.

        Raises:
            NonFiniteLossError: a member's loss is NaN or inf (nothing is backpropagated, and
                `step` must not follow).
        """
        if not torch.isfinite(loss_per_member).all():
            bad = loss_per_member.detach().cpu().tolist()
            raise NonFiniteLossError(f"{self.name} loss is not finite: {bad}; update not applied")
        with timed("backward"):
            loss_per_member.sum().backward()

    def step(self) -> torch.Tensor:
        """Clip each member's accumulated gradient and take the optimiser step; returns the
        grad norms [E] before clipping."""
        with timed("optimiser"):
            norms = clip_grad_norm_per_member(self.params, self.grad_norm_clip)
            self.optimiser.step()
        return norms


class TargetNet:
    """A frozen copy of a module, refreshed by hard copy every `interval` ticks: learner
    updates for the policy-gradient family (`maybe_update`), episodes for the value family
    (`EpisodeClock`)."""

    def __init__(self, module: nn.Module, interval: int):
        self.source = module
        self.interval = interval
        self.module = copy.deepcopy(module)
        self.module.requires_grad_(False)

    def copy_now(self) -> None:
        self.module.load_state_dict(self.source.state_dict())

    def maybe_update(self, updates: int) -> bool:
        if updates % self.interval == 0:
            self.copy_now()
            return True
        return False


class EpisodeClock:
    """Fires once each time the count of inserted episodes crosses a multiple of `interval`
    (the value family's target refresh: independent of actors, num_envs and update rate).

    Calling loop::

        clock = EpisodeClock(200)
        if clock.due(total_episodes):   # after an update
            target.copy_now()
    """

    def __init__(self, interval: int):
        self.interval = interval
        self.epoch = 0  # multiples of interval already acted on

    def due(self, episodes: int) -> bool:
        epoch = episodes // self.interval
        if epoch > self.epoch:
            self.epoch = epoch
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

    def sync_targets(self, episodes: int) -> bool:
        """Episode-counted target refresh (the value family's); the policy-gradient family
        refreshes its target critic every target_update_interval of its own updates, which
        its fixed data flow (a step per cycling.capacity-bounded round of new episodes) ties to
        the episode count."""
        return False

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


REWARD_NORMS = ("none", "scale", "standardise")


class RewardNorm:
    """Running reward statistics per ensemble member, applied to every batch a learner trains
    on: "scale" divides rewards by their running standard deviation, "standardise" also
    subtracts the running mean (EPyMARL's `standardise_rewards`), "none" leaves them alone.
    Statistics come from the real (unpadded) transitions of each batch before it is used.

    Shapes: reward, mask [E, B, T] -> [E, B, T].
    """

    def __init__(self, mode: str, n_ensemble: int, device: str = "cpu"):
        if mode not in REWARD_NORMS:
            raise ValueError(f"reward_norm {mode!r} is not one of {REWARD_NORMS}")
        self.mode = mode
        self.count = torch.zeros(n_ensemble, dtype=torch.float64, device=device)
        self.mean = torch.zeros(n_ensemble, dtype=torch.float64, device=device)
        self.m2 = torch.zeros(n_ensemble, dtype=torch.float64, device=device)

    def __call__(self, reward: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        if self.mode == "none":
            return reward
        dims = tuple(range(1, reward.dim()))
        n = mask.sum(dims).double()
        r = (reward * mask).double()
        b_mean = r.sum(dims) / n.clamp_min(1.0)
        b_m2 = (((reward.double() - b_mean.view(-1, *[1] * len(dims))) * mask) ** 2).sum(dims)
        total = self.count + n
        delta = b_mean - self.mean
        self.mean = self.mean + delta * n / total.clamp_min(1.0)
        self.m2 = self.m2 + b_m2 + delta**2 * self.count * n / total.clamp_min(1.0)
        self.count = total
        std = (self.m2 / self.count.clamp_min(1.0)).sqrt().clamp_min(1e-4)
        shape = (-1, *[1] * len(dims))
        out = reward / std.view(shape).float()
        if self.mode == "standardise":
            out = out - (self.mean / std).view(shape).float()
        return out * mask

    def state_dict(self) -> dict:
        return {"count": self.count, "mean": self.mean, "m2": self.m2}

    def load_state_dict(self, state: dict) -> None:
        self.count, self.mean, self.m2 = state["count"], state["mean"], state["m2"]
