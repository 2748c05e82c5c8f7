"""The centralised actor-critic family: CAC, E-CAC, M-CAC and EM-CAC (seed chapter 4, Alg. 2).

Decentralised GRU softmax actors (the shared AgentNet, logits masked by the available actions)
are trained by the policy gradient -log π(u_t^i | τ_t^i) A_t - β H(π(· | τ_t^i)) with one
central critic V(x_t), an MLP 64-64-1 over the joint observation x_t = (o_t^1, ..., o_t^N)
(the dissertation's critic never sees the state; `critic_input` can add it for comparison).
The critic regresses onto TD(λ) returns G_t built from a target critic copied every
`target_update_interval` updates; the advantage is A_t = G_t - V(x_t), shared by every agent,
divided by its standard deviation in the batch (`advantage_norm`, the default; not in the
dissertation).

    cac    fresh episodes only (the trainer's data plan hands over the newest run.num_envs)
    ecac   + the semi-online cycling buffer (main batch = the last 32 episodes, each used
           up to 8 times) and a second, critic-only pass on an off-policy `replay` batch
    mcac   + the KL mask (learner.kl_mask): a Polyak-averaged target policy; advantages of
           timesteps whose KL(π || π̃) exceeds K are zeroed
    emcac  both

Pure functions (policy log-probabilities, entropy, advantages, the policy loss) come first;
COMA (learner.coma) reuses them.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Literal

import torch

from buffer_service.episode import EpisodeBatch, EpisodeSchema
from learner.batch import TensorBatch, agent_inputs, joint_obs, masked_mean
from learner.common import AgentConfig, AgentCriticLearner, TargetNet, Updater
from learner.kl_mask import (
    categorical_kl,
    joint_kl,
    kl_keep_mask,
    masked_advantages,
    masked_fraction,
    polyak_update_,
)
from learner.networks import MLP, AgentNet, unroll
from learner.targets import lambda_returns

NEG = -1e10  # logit of an unavailable action: exp underflows to exactly 0, no inf/NaN


# -- pure functions ------------------------------------------------------------------------------
def masked_log_policy(logits: torch.Tensor, avail: torch.Tensor) -> torch.Tensor:
    """Log-probabilities of the softmax over the available actions.

    Rows without any available action (padding) are treated as all-available so they stay
    finite; the caller masks them out.

    Shapes: logits, avail [..., A] -> [..., A].
    """
    avail = avail | ~avail.any(-1, keepdim=True)
    return torch.log_softmax(logits.masked_fill(~avail, NEG), dim=-1)


def policy_entropy(logp: torch.Tensor, avail: torch.Tensor) -> torch.Tensor:
    """H(π) = -Σ_u π(u) log π(u) over the available actions. Shapes: [..., A] -> [...]."""
    terms = logp.exp() * logp
    return -torch.where(avail, terms, torch.zeros_like(terms)).sum(-1)


def actor_critic_advantages(
    reward: torch.Tensor,
    terminated: torch.Tensor,
    mask: torch.Tensor,
    target_values: torch.Tensor,
    values: torch.Tensor,
    gamma: float,
    lam: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """TD(λ) returns G from the target critic and advantages A = G - V from the critic.

    Args:
        reward, terminated, mask: [..., T].
        target_values: [..., T+1] target-critic values of every step and the one after.
        values: [..., T] the (online) critic's V(x_t).
        gamma, lam: discount and λ.
    Returns:
        (G, A), both [..., T], zero on padding.
    """
    g = lambda_returns(reward, terminated, mask, target_values, gamma, lam)
    return g, (g - values) * mask


def normalised_advantages(advantages: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """A / std(A) per member over the real entries (no mean shift: the critic stays the
    baseline), so that β weighs the same against the policy gradient on every map.

    Shapes: advantages, mask [E, ...] -> [E, ...] (zero on padding).
    """
    dims = tuple(range(1, advantages.dim()))
    n = mask.sum(dims, keepdim=True).clamp_min(1.0)
    mean = (advantages * mask).sum(dims, keepdim=True) / n
    var = ((advantages - mean).pow(2) * mask).sum(dims, keepdim=True) / n
    return advantages * mask / (var.sqrt() + 1e-8)


def policy_gradient_loss(
    logp_taken: torch.Tensor,
    advantages: torch.Tensor,
    entropy: torch.Tensor,
    mask: torch.Tensor,
    entropy_coef: float,
) -> torch.Tensor:
    """Per-member loss -mean(log π(u) A + β H) over the real (step, agent) entries.

    Args:
        logp_taken: [E, B, T, N] log-probability of the taken actions (with gradient).
        advantages: [E, B, T, N] (no gradient).
        entropy: [E, B, T, N] policy entropy (with gradient).
        mask: [E, B, T, N] 1 on real entries.
        entropy_coef: β.
    Returns:
        [E].
    """
    return -masked_mean(logp_taken * advantages.detach() + entropy_coef * entropy, mask)


def validate_actor_critic(cfg) -> None:
    """The checks every actor-critic config shares (CAC family, COMA): discount and λ in
    [0, 1], positive rates and clip, β >= 0, a target period >= 1 and positive critic widths."""
    for name in ("gamma", "td_lambda"):
        if not 0.0 <= getattr(cfg, name) <= 1.0:
            raise ValueError(f"{name} must be in [0, 1], got {getattr(cfg, name)}")
    for name in ("lr", "critic_lr", "grad_norm_clip"):
        if getattr(cfg, name) <= 0:
            raise ValueError(f"{name} must be > 0, got {getattr(cfg, name)}")
    if cfg.entropy_coef < 0:
        raise ValueError(f"entropy_coef must be >= 0, got {cfg.entropy_coef}")
    if cfg.target_update_interval < 1:
        raise ValueError(f"target_update_interval must be >= 1, got {cfg.target_update_interval}")
    if not cfg.critic_hidden or min(cfg.critic_hidden) < 1:
        raise ValueError(
            f"critic_hidden needs at least one positive width, got {cfg.critic_hidden}"
        )


# -- config and learner ---------------------------------------------------------------------------
@dataclass(frozen=True)
class CACConfig:
    """Hyper-parameters of CAC, E-CAC, M-CAC and EM-CAC (seed 5.3.4; λ from the SMAC paper's COMA).

    Attributes:
        gamma: discount.
        lr: Adam learning rate of the actors.
        critic_lr: Adam learning rate of the critic.
        grad_norm_clip: per-seed gradient norm clip (actors and critic separately).
        td_lambda: λ of the TD(λ) returns.
        entropy_coef: β, weight of the policy-entropy bonus.
        target_update_interval: updates between hard copies into the target critic.
        critic_hidden: hidden widths of the central critic MLP.
        critic_input: what the critic sees: "obs" (joint observation, the dissertation's choice),
            "state" or "obs_state" (both, concatenated).
        kl_threshold: K; masked variants zero the advantage where KL(π || π̃) > K.
        polyak_tau: τ of the target policy π̃ <- (1 - τ) π̃ + τ π after every update.
        kl_granularity: "agent" masks each (step, agent) by that agent's KL; "joint" masks
            whole steps by the joint policy's KL (the sum over agents).
        advantage_norm: divide the advantages by their standard deviation in each batch,
            so that β weighs the same against the policy gradient on every map (not in the
            seed; on by default since it made EM-CAC learn skirmish/2s3z and 3s5z, where
            the raw advantages are 2-2.5x smaller than on 3m: results/pg/README.md).
        agent: the shared agent network.
    """

    gamma: float = 0.99
    lr: float = 5e-4
    critic_lr: float = 5e-4
    grad_norm_clip: float = 10.0
    td_lambda: float = 0.8
    entropy_coef: float = 0.1
    target_update_interval: int = 200
    critic_hidden: tuple[int, ...] = (64, 64)
    critic_input: Literal["obs", "state", "obs_state"] = "obs"
    kl_threshold: float = 0.05
    polyak_tau: float = 0.05
    kl_granularity: Literal["agent", "joint"] = "agent"
    advantage_norm: bool = True
    agent: AgentConfig = field(default_factory=AgentConfig)

    def validate(self) -> None:
        validate_actor_critic(self)
        if self.kl_threshold <= 0:
            raise ValueError(f"kl_threshold must be > 0, got {self.kl_threshold}")
        if not 0.0 < self.polyak_tau <= 1.0:
            raise ValueError(f"polyak_tau must be in (0, 1], got {self.polyak_tau}")


def critic_features(tb: TensorBatch, kind: str) -> torch.Tensor:
    """The central critic's input at every step: [E, B, T+1, D]."""
    if kind == "obs":
        return joint_obs(tb.obs)
    if kind == "state":
        return tb.state
    return torch.cat([joint_obs(tb.obs), tb.state], dim=-1)


class CACLearner(AgentCriticLearner):
    """The CAC family; `extended` and `masked` select the variant (module docstring).

    Calling loop::

        learner = CACLearner(cfg, schema, extended=True, masked=True, n_ensemble=1)
        metrics = learner.step(batch, extra)   # batch: cycling table, extra: replay batch
        weights = learner.get_weights()        # actors sample the masked softmax
    """

    policy_kind = "softmax"

    def __init__(
        self,
        cfg: CACConfig,
        info: EpisodeSchema,
        extended: bool = False,
        masked: bool = False,
        n_ensemble: int = 1,
        device: str = "cpu",
    ):
        self.cfg, self.info, self.extended, self.masked = cfg, info, extended, masked
        self.n_ensemble, self.device = n_ensemble, device
        n = info.n_agents
        self.acting = cfg.agent.acting_spec(info, self.policy_kind)
        self.agent = self.acting.build(n_ensemble).to(device)
        in_dim = {"obs": n * info.obs_dim, "state": info.state_dim}.get(
            cfg.critic_input, n * info.obs_dim + info.state_dim
        )
        self.critic = MLP(n_ensemble, in_dim, tuple(cfg.critic_hidden), 1).to(device)
        self.target_critic = TargetNet(self.critic, cfg.target_update_interval)
        self.target_policy: AgentNet | None = None
        if masked:
            self.target_policy = copy.deepcopy(self.agent).requires_grad_(False)
        self.critic_updater = Updater(
            list(self.critic.parameters()), cfg.critic_lr, cfg.grad_norm_clip, "CAC critic"
        )
        self.agent_updater = Updater(
            list(self.agent.parameters()), cfg.lr, cfg.grad_norm_clip, "CAC policy"
        )
        self.updates = 0

    def values(self, tb: TensorBatch, critic: MLP) -> torch.Tensor:
        """V of every step, [E, B, T+1]."""
        x = critic_features(tb, self.cfg.critic_input)
        e, b, tp, d = x.shape
        return critic(x.reshape(e, b * tp, d)).view(e, b, tp)

    def critic_pass(self, tb: TensorBatch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One critic update towards TD(λ) returns of the target critic.

        Returns:
            (per-member loss [E], G [E, B, T], A [E, B, T]) with A from the critic's values
            before this update (seed Algorithm 2, lines 16-20).
        """
        t = tb.shape[2]
        with torch.no_grad():
            target_v = self.values(tb, self.target_critic.module)
        v = self.values(tb, self.critic)[:, :, :t]
        cfg = self.cfg
        g, adv = actor_critic_advantages(
            tb.reward, tb.terminated, tb.mask, target_v, v.detach(), cfg.gamma, cfg.td_lambda
        )
        loss = masked_mean((v - g).pow(2), tb.mask)
        self.critic_updater.apply(loss)
        return loss.detach(), g, adv

    def kl_mask(
        self, tb: TensorBatch, inputs: torch.Tensor, logp: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """KL(π || π̃) per (step, agent) [E, B, T, N] and the keep mask (1 = advantage kept)."""
        assert self.target_policy is not None
        t = tb.shape[2]
        with torch.no_grad():
            avail = tb.avail[:, :, :t]
            logq = masked_log_policy(unroll(self.target_policy, inputs)[:, :, :t], avail)
            kl = categorical_kl(logp.detach(), logq, avail)
            if self.cfg.kl_granularity == "joint":
                kl = joint_kl(kl)
            return kl, kl_keep_mask(kl, self.cfg.kl_threshold)

    def step(self, batch: EpisodeBatch, extra: EpisodeBatch | None = None) -> dict[str, float]:
        """Critic update, masked policy-gradient update, then (extended variants, when `extra`
        is given) a critic-only pass on the off-policy batch; returns scalar metrics."""
        tb = TensorBatch.from_episodes(batch, self.device)
        e, b, t, n = tb.shape
        loss_c, g, adv = self.critic_pass(tb)
        if self.cfg.advantage_norm:
            adv = normalised_advantages(adv, tb.mask)

        inputs = agent_inputs(tb.obs, tb.actions, self.info.n_actions)
        avail = tb.avail[:, :, :t]
        logp = masked_log_policy(unroll(self.agent, inputs)[:, :, :t], avail)
        logp_taken = logp.gather(-1, tb.actions.unsqueeze(-1)).squeeze(-1)
        entropy = policy_entropy(logp, avail)
        mask = tb.mask.unsqueeze(-1).expand(e, b, t, n)
        adv_n = adv.unsqueeze(-1).expand(e, b, t, n)
        metrics: dict[str, float] = {}
        if self.masked:
            kl, keep = self.kl_mask(tb, inputs, logp)
            adv_n = masked_advantages(adv_n, keep)
            metrics["kl_mean"] = float(masked_mean(kl, mask).mean())
            metrics["kl_masked_fraction"] = float(masked_fraction(keep, mask).mean())
        loss_pi = policy_gradient_loss(logp_taken, adv_n, entropy, mask, self.cfg.entropy_coef)
        norms = self.agent_updater.apply(loss_pi)

        if self.extended and extra is not None:
            loss_x, _, _ = self.critic_pass(TensorBatch.from_episodes(extra, self.device))
            metrics["loss_critic_extra"] = float(loss_x.mean())
        self.updates += 1
        self.target_critic.maybe_update(self.updates)
        if self.target_policy is not None:
            polyak_update_(self.target_policy, self.agent, self.cfg.polyak_tau)
        metrics.update(
            loss_critic=float(loss_c.mean()),
            loss_policy=float(loss_pi.detach().mean()),
            entropy=float(masked_mean(entropy.detach(), mask).mean()),
            return_mean=float(masked_mean(g, tb.mask).mean()),
            advantage_abs_mean=float(masked_mean(adv.abs(), tb.mask).mean()),
            grad_norm_policy=float(norms.mean()),
        )
        return metrics

    def extra_modules(self) -> dict:
        return {"target_policy": self.target_policy}
