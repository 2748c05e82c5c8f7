"""COMA, counterfactual multi-agent policy gradients (Foerster et al., 2018): the dissertation's PG
baseline.

A centralised critic Q(s, u^-a, ·) gives, for agent a, the value of each of a's actions with
the other agents' actions held at what they did. Its input per agent is the global state, a's
own observation, every other agent's current action one-hot (a's own block zeroed), everyone's
previous action one-hot and a's id one-hot. The critic regresses Q(s, u)[u^a] onto TD(λ)
returns built from a target critic. Each agent's advantage is the counterfactual one,

    A^a = Q(s, u)[u^a] - Σ_u' π^a(u' | τ^a) Q(s, u^-a, u'),

and the decentralised GRU softmax actors follow -log π^a(u^a) A^a - β H(π^a).

The episode recorder stores no action for the state after an episode's last transition, so
the bootstrap Q of a time-limit cut takes every agent's most probable available action there
under the current policy (terminal steps never bootstrap).

The critic is trained with one batched update per step (the SMAC paper's PyMARL code steps it
once per timestep instead); one update keeps COMA's schedule comparable with CAC's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch.nn import functional as F

from buffer_service.episode import EpisodeBatch, EpisodeSchema
from learner.batch import TensorBatch, agent_inputs, masked_mean
from learner.common import AgentConfig, AgentCriticLearner, TargetNet, Updater
from learner.networks import MLP, unroll
from learner.pg import (
    masked_log_policy,
    policy_entropy,
    policy_gradient_loss,
    validate_actor_critic,
)
from learner.targets import lambda_returns


def coma_advantages(q: torch.Tensor, logp: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Counterfactual advantages Q[u^a] - Σ_u π^a(u) Q[u].

    Args:
        q: [..., A] the critic's Q(s, u^-a, ·) for each agent.
        logp: [..., A] the agent's log-policy (probabilities of unavailable actions are 0).
        actions: [...] taken actions.
    Returns:
        [...].
    """
    baseline = (logp.exp() * q).sum(-1)
    return q.gather(-1, actions.unsqueeze(-1)).squeeze(-1) - baseline


@dataclass(frozen=True)
class COMAConfig:
    """Hyper-parameters of COMA (SMAC paper / PyMARL values, as the dissertation used; Adam as CAC).

    Attributes:
        gamma: discount.
        lr: Adam learning rate of the actors.
        critic_lr: Adam learning rate of the critic.
        grad_norm_clip: per-seed gradient norm clip (actors and critic separately).
        td_lambda: λ of the critic's TD(λ) targets.
        entropy_coef: β, weight of the policy-entropy bonus (as CAC, for a fair comparison).
        target_update_interval: updates between hard copies into the target critic.
        critic_hidden: hidden widths of the critic MLP (its output has n_actions units).
        agent: the shared agent network.
    """

    gamma: float = 0.99
    lr: float = 5e-4
    critic_lr: float = 5e-4
    grad_norm_clip: float = 10.0
    td_lambda: float = 0.8
    entropy_coef: float = 0.1
    target_update_interval: int = 200
    critic_hidden: tuple[int, ...] = (128, 128)
    agent: AgentConfig = field(default_factory=AgentConfig)

    def validate(self) -> None:
        validate_actor_critic(self)


class COMALearner(AgentCriticLearner):
    """Counterfactual critic update, then the actors' policy-gradient update.

    Calling loop::

        learner = COMALearner(cfg, schema, n_ensemble=1)
        metrics = learner.step(batch)          # fresh episodes
    """

    policy_kind = "softmax"

    def __init__(
        self, cfg: COMAConfig, info: EpisodeSchema, n_ensemble: int = 1, device: str = "cpu"
    ):
        self.cfg, self.info, self.n_ensemble, self.device = cfg, info, n_ensemble, device
        n, a = info.n_agents, info.n_actions
        self.acting = cfg.agent.acting_spec(info, self.policy_kind)
        self.agent = self.acting.build(n_ensemble).to(device)
        in_dim = info.state_dim + info.obs_dim + 2 * n * a + n
        self.critic = MLP(n_ensemble, in_dim, tuple(cfg.critic_hidden), a).to(device)
        self.target_critic = TargetNet(self.critic, cfg.target_update_interval)
        self.critic_updater = Updater(
            list(self.critic.parameters()), cfg.critic_lr, cfg.grad_norm_clip, "COMA critic"
        )
        self.agent_updater = Updater(
            list(self.agent.parameters()), cfg.lr, cfg.grad_norm_clip, "COMA policy"
        )
        self.updates = 0

    def critic_inputs(self, tb: TensorBatch, actions: torch.Tensor) -> torch.Tensor:
        """Per-agent inputs [state, own obs, others' actions, previous joint action, id].

        Args:
            tb: the batch (obs, state of T+1 steps).
            actions: [E, B, T+1, N] the joint action at every step (bootstrap step included).
        Returns:
            [E, B, T+1, N, S + O + 2 N A + N].
        """
        e, b, tp, n = actions.shape
        a = self.info.n_actions
        joint = F.one_hot(actions, a).float().reshape(e, b, tp, 1, n * a).expand(e, b, tp, n, n * a)
        own = torch.eye(n, device=actions.device).repeat_interleave(a, dim=1)  # [N, N*A]
        others = joint * (1.0 - own)
        prev = torch.cat([torch.zeros_like(joint[:, :, :1]), joint[:, :, :-1]], dim=2)
        state = tb.state.unsqueeze(3).expand(e, b, tp, n, tb.state.shape[-1])
        ids = torch.eye(n, device=actions.device).expand(e, b, tp, n, n)
        return torch.cat([state, tb.obs, others, prev, ids], dim=-1)

    def q_values(self, critic: MLP, x: torch.Tensor) -> torch.Tensor:
        """[E, B, T', N, D] -> Q [E, B, T', N, A]."""
        e, b, tp, n, d = x.shape
        return critic(x.reshape(e, b * tp * n, d)).view(e, b, tp, n, -1)

    def step(self, batch: EpisodeBatch, extra: EpisodeBatch | None = None) -> dict[str, float]:
        """One critic update and one actor update (`extra` is unused); returns scalar metrics."""
        tb = TensorBatch.from_episodes(batch, self.device)
        e, b, t, n = tb.shape
        inputs = agent_inputs(tb.obs, tb.actions, self.info.n_actions)
        logp_all = masked_log_policy(unroll(self.agent, inputs), tb.avail)  # [E, B, T+1, N, A]
        # Real actions where recorded; the most probable available action elsewhere (the
        # bootstrap step after each episode's end, and padding, which is masked out).
        real = torch.cat([tb.mask, tb.mask.new_zeros(e, b, 1)], dim=2).bool().unsqueeze(-1)
        recorded = torch.cat([tb.actions, tb.actions.new_zeros(e, b, 1, n)], dim=2)
        actions = torch.where(real, recorded, logp_all.detach().argmax(-1))
        x = self.critic_inputs(tb, actions)
        with torch.no_grad():
            tq = self.q_values(self.target_critic.module, x)
            tq_taken = tq.gather(-1, actions.unsqueeze(-1)).squeeze(-1)  # [E, B, T+1, N]
            per_agent = [t_.unsqueeze(2).expand(e, b, n, t) for t_ in (tb.reward, tb.terminated)]
            mask_n = tb.mask.unsqueeze(2).expand(e, b, n, t)
            g = lambda_returns(
                *per_agent, mask_n, tq_taken.transpose(2, 3), self.cfg.gamma, self.cfg.td_lambda
            ).transpose(2, 3)  # [E, B, T, N]
        q = self.q_values(self.critic, x[:, :, :t])
        q_taken = q.gather(-1, tb.actions.unsqueeze(-1)).squeeze(-1)
        mask = tb.mask.unsqueeze(-1).expand(e, b, t, n)
        loss_c = masked_mean((q_taken - g).pow(2), mask)
        self.critic_updater.apply(loss_c)

        logp = logp_all[:, :, :t]
        adv = coma_advantages(q.detach(), logp.detach(), tb.actions) * mask
        logp_taken = logp.gather(-1, tb.actions.unsqueeze(-1)).squeeze(-1)
        entropy = policy_entropy(logp, tb.avail[:, :, :t])
        loss_pi = policy_gradient_loss(logp_taken, adv, entropy, mask, self.cfg.entropy_coef)
        norms = self.agent_updater.apply(loss_pi)
        self.updates += 1
        self.target_critic.maybe_update(self.updates)
        return {
            "loss_critic": float(loss_c.detach().mean()),
            "loss_policy": float(loss_pi.detach().mean()),
            "entropy": float(masked_mean(entropy.detach(), mask).mean()),
            "q_taken_mean": float(masked_mean(q_taken.detach(), mask).mean()),
            "advantage_abs_mean": float(masked_mean(adv.abs(), mask).mean()),
            "grad_norm_policy": float(norms.mean()),
        }
