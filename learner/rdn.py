"""RDN, the Relevance Decomposition Network (seed chapter 4, Algorithm 1).

A central critic Q_c(x) over every agent's last `obs_window` observations, current action
one-hot and id one-hot is trained by TD. Its value for the taken joint action is split into
per-agent targets by LRP (`learner.lrp`): agent i's target is the relevance summed over its
own input block, and each agent's Q_i(o_i, u_i) is regressed onto it. The state is never used.

Next action in the critic's TD target (`next_action`):
* "greedy" (default): each agent's greedy action under the current agent network (the joint
  action the agents would actually take), which scales to any number of agents;
* "local_max": the best of the greedy joint action and every joint action that moves one
  agent's action away from it (N·(A-1) + 1 candidates, from one counterfactual pass of the
  critic), chosen by the online critic and valued by the target critic (double Q-learning's
  split), so the critic's target improves on the agents' greedy policy as Q-learning's max
  does, at any number of agents;
* "joint_max": the maximum of the target critic over every joint action, exact centralised
  Q-learning, only possible when A^N is small (<= `joint_max_limit`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Literal

import torch

from buffer_service.episode import EpisodeBatch, EpisodeSchema
from learner.batch import (
    AllSteps,
    RealSteps,
    TensorBatch,
    agent_blocks,
    agent_inputs,
    greedy_actions,
    masked_mean,
)
from learner.common import (
    AgentConfig,
    AgentCriticLearner,
    EpisodeClock,
    RewardNorm,
    TargetNet,
    Updater,
    validate_value_schedule,
)
from learner.lrp import (
    LRP_RULES,
    AgentRelevance,
    agent_relevance,
    agent_relevance_all_actions,
    critic_all_actions,
    lrp_difference,
    lrp_epsilon,
)
from learner.networks import MLP, AgentBlockLinear, unroll
from learner.targets import q_lambda_targets


@dataclass(frozen=True)
class RDNConfig:
    """Hyper-parameters of RDN (seed 5.3.3).

    Attributes:
        gamma: discount.
        lr: learning rate of the critic (and of the agents, times agent_lr_scale).
        agent_lr_scale: the agents' learning rate as a multiple of lr (1: the seed's one rate).
        grad_norm_clip: per-seed gradient norm clip.
        target_update_episodes: inserted episodes between hard copies into the target critic
            (as the value family's).
        optimiser: "adam" or "rmsprop".
        reward_norm: "none", "scale" or "standardise" (as the value family's).
        td_lambda: λ of the critic's Q(λ) targets (0: one-step TD).
        critic_hidden: hidden widths of the central critic MLP.
        critic_agent_encoder: 0 (the seed's critic: the MLP acts on the concatenated blocks) or
            the width H of a first layer shared by every agent's block (`AgentBlockLinear`:
            agent i's block -> its own H units, the same weights for all agents), before the
            `critic_hidden` layers. Still a ReLU MLP over the same input, so LRP is unchanged.
        obs_window: how many of each agent's latest observations the critic sees.
        lrp_rule: relevance rule, one of learner.lrp.LRP_RULES.
        lrp_eps: ε of the LRP-ε rule.
        next_action: "greedy", "local_max" or "joint_max" (module docstring).
        agent_targets: "taken" (the seed's: Q_i(o_i, u_i) of the taken action regresses onto
            agent i's LRP share of Q_c(x)) or "all_actions" (every available action a of
            agent i regresses onto its LRP share of Q_c with its action moved to a, the
            others' actions fixed) or "counterfactual" (the taken action's target is its
            LRP share; every other available action a gets that share plus the critic's own
            difference Q_c(x with agent i's action a) - Q_c(x), so the agent's action ranking
            is the critic's and its level is its LRP credit).
        lrp_reference: "zero" (the seed's LRP-ε of the critic's value) or "no_actions" (the
            value without actions split by LRP-ε, the actions' difference split by the ε-rule
            on deviations; `RDNLearner.agent_targets`).
        split_critic: which critic the agents' targets are split from: "online" (the seed's:
            the critic just updated on this batch) or "target" (the target critic, fixed for
            target_update_episodes episodes, so the agents regress onto a function that holds
            still between refreshes, as the value family's TD targets do).
        split_actions: the joint action the agents' targets are split at: "taken" (the
            seed's: the joint action in the replay, whose teammates' actions include the
            behaviour policy's exploration) or "greedy" (every agent's greedy action under the
            current agent network, the joint action the team would take; the taken action is
            not special). With agent_targets "counterfactual", agent i's target for action a is
            then its LRP share of Q_c at the greedy joint action plus Q_c(a, greedy_-i) -
            Q_c(greedy): a best response to the teammates' greedy actions, not to their
            exploratory ones. Needs agent_targets "counterfactual" or "all_actions".
        joint_max_limit: largest joint action space "joint_max" may enumerate.
        agent: the shared agent network.
    """

    gamma: float = 0.99
    lr: float = 5e-4
    agent_lr_scale: float = 1.0
    grad_norm_clip: float = 10.0
    target_update_episodes: int = 200
    optimiser: Literal["adam", "rmsprop"] = "adam"
    reward_norm: Literal["none", "scale", "standardise"] = "none"
    td_lambda: float = 0.0
    critic_hidden: tuple[int, ...] = (64, 64)
    critic_agent_encoder: int = 0
    obs_window: int = 4
    lrp_rule: Literal["eps_residual", "eps", "eps_nobias", "grad_x_input"] = "eps_residual"
    lrp_eps: float = 0.01
    next_action: Literal["greedy", "local_max", "joint_max"] = "greedy"
    agent_targets: Literal["taken", "all_actions", "counterfactual"] = "taken"
    lrp_reference: Literal["zero", "no_actions"] = "zero"
    split_critic: Literal["online", "target"] = "online"
    split_actions: Literal["taken", "greedy"] = "taken"
    joint_max_limit: int = 1024
    agent: AgentConfig = field(default_factory=AgentConfig)

    def validate(self) -> None:
        validate_value_schedule(
            self.gamma,
            self.lr,
            self.grad_norm_clip,
            self.target_update_episodes,
            self.optimiser,
            self.reward_norm,
            self.td_lambda,
        )
        if self.agent_lr_scale <= 0:
            raise ValueError(f"agent_lr_scale must be > 0, got {self.agent_lr_scale}")
        if self.split_critic not in ("online", "target"):
            raise ValueError(
                f"split_critic must be 'online' or 'target', got {self.split_critic!r}"
            )
        if self.split_actions not in ("taken", "greedy"):
            raise ValueError(
                f"split_actions must be 'taken' or 'greedy', got {self.split_actions!r}"
            )
        if self.split_actions == "greedy" and self.agent_targets == "taken":
            raise ValueError(
                "split_actions=greedy needs agent_targets=counterfactual or all_actions "
                "(agent_targets=taken trains only the taken action)"
            )
        if self.lrp_eps <= 0:
            raise ValueError(f"lrp_eps must be > 0, got {self.lrp_eps}")
        if self.critic_agent_encoder < 0:
            raise ValueError(f"critic_agent_encoder must be >= 0, got {self.critic_agent_encoder}")
        for name in ("obs_window", "joint_max_limit"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.critic_hidden or min(self.critic_hidden) < 1:
            raise ValueError(
                f"critic_hidden needs at least one positive width, got {self.critic_hidden}"
            )
        if self.lrp_rule not in LRP_RULES:
            raise ValueError(f"lrp_rule must be one of {LRP_RULES}")
        if self.agent_targets == "all_actions" and self.lrp_reference != "zero":
            raise ValueError("agent_targets=all_actions needs lrp_reference=zero")
        if self.agent_targets == "all_actions" and self.lrp_rule == "grad_x_input":
            raise ValueError(
                "agent_targets=all_actions needs an epsilon lrp_rule, not grad_x_input"
            )


class RDNLearner(AgentCriticLearner):
    """Critic TD update, then agent update toward LRP shares of the updated critic's value.

    Calling loop::

        learner = RDNLearner(cfg, schema, n_ensemble=1)
        metrics = learner.step(batch)
    """

    policy_kind = "q"

    def __init__(
        self, cfg: RDNConfig, info: EpisodeSchema, n_ensemble: int = 1, device: str = "cpu"
    ):
        self.cfg, self.info, self.n_ensemble, self.device = cfg, info, n_ensemble, device
        n, a = info.n_agents, info.n_actions
        if cfg.next_action == "joint_max" and a**n > cfg.joint_max_limit:
            raise ValueError(
                f"algo.next_action=joint_max would enumerate {a}^{n} joint actions "
                f"(> joint_max_limit={cfg.joint_max_limit}); use next_action=greedy"
            )
        self.block = cfg.obs_window * info.obs_dim + a + n
        self.acting = cfg.agent.acting_spec(info, self.policy_kind)
        self.agent = self.acting.build(n_ensemble).to(device)
        first = None
        if cfg.critic_agent_encoder:
            first = AgentBlockLinear(n_ensemble, n, self.block, cfg.critic_agent_encoder)
        self.critic = MLP(n_ensemble, n * self.block, tuple(cfg.critic_hidden), 1, first).to(device)
        self.target_critic = TargetNet(self.critic, cfg.target_update_episodes)
        self.clock = EpisodeClock(cfg.target_update_episodes)
        self.reward_norm = RewardNorm(cfg.reward_norm, n_ensemble, device)
        self.critic_updater = Updater(
            list(self.critic.parameters()), cfg.lr, cfg.grad_norm_clip, "RDN critic", cfg.optimiser
        )
        self.agent_updater = Updater(
            list(self.agent.parameters()),
            cfg.lr * cfg.agent_lr_scale,
            cfg.grad_norm_clip,
            "RDN agent",
            cfg.optimiser,
        )
        self.updates = 0
        # the critic skips padded steps where it can (`critic_steps`); False computes them too
        # (the same values up to float rounding: for checks)
        self.pack_steps = True

    def sync_targets(self, episodes: int) -> bool:
        """Copy the critic into the target critic every target_update_episodes episodes."""
        if not self.clock.due(episodes):
            return False
        self.target_critic.copy_now()
        return True

    def critic_inputs(self, hist: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Per-agent blocks [history, action one-hot, id one-hot] laid end to end
        (`learner.batch.agent_blocks`: kept as its parts when hist is a window view, so the
        critic and LRP multiply each observation once; dense otherwise, the same values).

        Shapes: hist [E, B, T', N, W*O], actions [E, B, T', N] -> [E, B*T', N*block].
        """
        return agent_blocks(hist, actions, self.info.n_actions, self.cfg.obs_window)

    def _next_value(
        self, hist_next: torch.Tensor, qs_next: torch.Tensor, avail_next: torch.Tensor
    ) -> torch.Tensor:
        """Target critic value of the next step, [E, B, T]."""
        e, b, t, n, _ = hist_next.shape
        critic = self.target_critic.module
        if self.cfg.next_action != "joint_max":
            greedy = greedy_actions(qs_next, avail_next)
            if self.cfg.next_action == "local_max":
                greedy = self._best_deviation(hist_next, greedy, avail_next)
            return critic(self.critic_inputs(hist_next, greedy)).view(e, b, t)
        joint = torch.tensor(
            list(itertools.product(range(self.info.n_actions), repeat=n)), device=self.device
        )
        values = []
        for ja in joint:  # A^N is small here by construction (joint_max_limit)
            acts = ja.expand(e, b, t, n)
            allowed = avail_next.gather(-1, acts.unsqueeze(-1)).squeeze(-1).all(-1)
            v = critic(self.critic_inputs(hist_next, acts)).view(e, b, t)
            values.append(v.masked_fill(~allowed, -1e10))
        return torch.stack(values, -1).max(-1).values

    def _best_deviation(
        self, hist_next: torch.Tensor, greedy: torch.Tensor, avail_next: torch.Tensor
    ) -> torch.Tensor:
        """The joint action among `greedy` and its single-agent deviations that the online
        critic values most (next_action "local_max"), [E, B, T, N].

        Shapes: hist_next [E, B, T, N, W*O], greedy [E, B, T, N], avail_next [E, B, T, N, A].
        """
        e, b, t, n = greedy.shape
        a = self.info.n_actions
        x = self.critic_inputs(hist_next, greedy)
        offset = self.cfg.obs_window * self.info.obs_dim
        avail = avail_next.reshape(e, b * t, n, a)  # only the available deviations
        q = critic_all_actions(self.critic, x, greedy.reshape(e, b * t, n), n, offset, a, avail)
        q = q.view(e, b, t, n, a).masked_fill(~avail_next, float("-inf"))
        best = q.view(e, b, t, n * a).argmax(-1)  # the greedy action itself is a candidate
        agent, action = best // a, best % a
        moved = torch.nn.functional.one_hot(agent, n).bool()
        return torch.where(moved, action.unsqueeze(-1), greedy)

    @property
    def split_module(self) -> MLP:
        """The critic the agents' targets are split from (RDNConfig.split_critic)."""
        return self.critic if self.cfg.split_critic == "online" else self.target_critic.module

    def agent_targets(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(shares [E, M, N], Q_c(x) [E, M]): `_split` without its third part."""
        shares, q, _ = self._split(x)
        return shares, q

    def _split(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, AgentRelevance | None]:
        """Each agent's LRP share of the critic's value for critic inputs x [E, M, N*block]:
        (shares [E, M, N], Q_c(x) [E, M], the relevance itself when LRP ran on the structured
        input, whose forward pass `critic_all_actions` reuses, else None).

        lrp_reference "zero" (the seed's): LRP-ε of Q_c(x), agent i's share the relevance of
        its block. "no_actions": the same split of Q_c(x̄), x̄ = x with every action one-hot
        removed (what the agents' observations are worth), plus each agent's relevance in the
        difference Q_c(x) - Q_c(x̄) (`lrp_difference`), which only the action bits carry; the
        shares still add up to Q_c(x).
        """
        cfg, n = self.cfg, self.info.n_agents
        if cfg.lrp_reference == "zero":
            relevance, q = lrp_epsilon(self.split_module, x, cfg.lrp_eps, cfg.lrp_rule)
            structured = isinstance(relevance, AgentRelevance)
            return agent_relevance(relevance, n), q, relevance if structured else None
        e, m, _ = x.shape
        start = cfg.obs_window * self.info.obs_dim
        x_ref = x.view(e, m, n, self.block).clone()
        x_ref[..., start : start + self.info.n_actions] = 0.0
        x_ref = x_ref.view_as(x)
        base, q_ref = lrp_epsilon(self.split_module, x_ref, cfg.lrp_eps, cfg.lrp_rule)
        diff, delta = lrp_difference(self.split_module, x, x_ref, cfg.lrp_eps)
        return agent_relevance(base, n) + agent_relevance(diff, n), q_ref + delta, None

    def split_joint_action(
        self, qs: torch.Tensor, actions: torch.Tensor, avail: torch.Tensor
    ) -> torch.Tensor:
        """The joint action the agents' targets are split at (RDNConfig.split_actions): the
        taken `actions` themselves, or every agent's greedy action under its Q-values `qs`
        among the available ones.

        Shapes: qs [E, B, T, N, A], actions [E, B, T, N], avail [E, B, T, N, A] -> [E, B, T, N].
        """
        if self.cfg.split_actions == "taken":
            return actions
        return greedy_actions(qs, avail)

    def _every_action_targets(
        self,
        x: torch.Tensor,
        actions: torch.Tensor,
        shares: torch.Tensor,
        q_tot: torch.Tensor,
        trained: torch.Tensor,
        lrp: AgentRelevance | None = None,
    ) -> torch.Tensor:
        """Targets [E, B, T, N, A] for agent_targets "all_actions" or "counterfactual" (see
        RDNConfig), from critic inputs x, the taken actions [E, B, T, N], their LRP shares
        [E, B, T, N], Q_c(x) [E, B*T] and the entries the agents' loss uses [E, B, T, N, A]
        (the counterfactual critic runs on those only; the others are not used), and the
        relevance `_split` computed on x if known."""
        e, b, t, n = actions.shape
        args = (x, actions.reshape(e, b * t, n), n, self.cfg.obs_window * self.info.obs_dim)
        if self.cfg.agent_targets == "all_actions":
            every = agent_relevance_all_actions(
                self.split_module, *args, self.info.n_actions, self.cfg.lrp_eps, self.cfg.lrp_rule
            )
            return every.view(e, b, t, n, -1)
        a = self.info.n_actions
        keep = trained.view(e, b * t, n, a)
        q_alt = critic_all_actions(self.split_module, *args, a, keep, lrp, q_tot)
        every = q_alt.view(e, b, t, n, a).sub_(q_tot.view(e, b, t, 1, 1))  # in place: fresh
        return every.add_(shares.unsqueeze(-1))

    def critic_steps(self, tb: TensorBatch) -> AllSteps | RealSteps:
        """The critic's layout of the batch's steps: the real steps packed together when the
        critic sees one observation per agent (`RealSteps`, the same values without computing
        anything for padding), else every step (`AllSteps`)."""
        if self.cfg.obs_window == 1 and self.pack_steps:
            return RealSteps(tb)
        return AllSteps(tb, self.cfg.obs_window)

    def step(self, batch: EpisodeBatch, extra: EpisodeBatch | None = None) -> dict[str, float]:
        """One RDN update (critic, then agents; `extra` is unused); returns scalar metrics.

        The critic side runs on `self.critic_steps(tb)`'s layout, [E, B', T', ...]: every
        step, or the real steps packed; the agents' Q-values are taken into it, and the next
        values put back for the Q(λ) targets, which need the episodes' time order."""
        tb = TensorBatch.from_episodes(batch, self.device)
        n, a = self.info.n_agents, self.info.n_actions
        steps = self.critic_steps(tb)
        qs_all = unroll(self.agent, agent_inputs(tb.obs, tb.actions, a))  # [E, B, T+1, N, A]
        qs, actions, avail = steps.take(qs_all), steps.take(tb.actions), steps.take(tb.avail)
        e, b, t = steps.mask.shape
        x = self.critic_inputs(steps.hist(), actions)
        with torch.no_grad():
            v_next = self._next_value(
                steps.hist(1), steps.take(qs_all.detach(), 1), steps.take(tb.avail, 1)
            )
            reward = self.reward_norm(tb.reward, tb.mask)
            v_next = steps.put(v_next)  # [E, B, T]: the targets run along each episode
            y = q_lambda_targets(
                reward, tb.terminated, tb.mask, v_next, self.cfg.gamma, self.cfg.td_lambda
            )
            y = steps.take(y)
        q_c = self.critic(x).view(e, b, t)
        critic_loss = masked_mean((q_c - y).pow(2), steps.mask)
        self.critic_updater.apply(critic_loss)

        acts = self.split_joint_action(qs, actions, avail)
        if acts is not actions:
            x = self.critic_inputs(steps.hist(), acts)
        targets, q_tot, lrp = self._split(x)
        targets = targets.view(e, b, t, n)
        if self.cfg.agent_targets == "taken":
            chosen = qs.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
            mask = steps.mask.unsqueeze(-1).expand_as(chosen)
            agent_loss = masked_mean((chosen - targets).pow(2), mask)
        else:  # a target for every available action of every agent
            ok = avail & steps.mask.bool()[..., None, None]
            every = self._every_action_targets(x, acts, targets, q_tot, ok, lrp)
            agent_loss = masked_mean((qs - every).pow(2), ok.float())
        self.agent_updater.apply(agent_loss)

        self.updates += 1
        gap = (targets.sum(-1) - q_tot.view(e, b, t)).abs()
        return {
            "loss_critic": float(critic_loss.detach().mean()),
            "loss_agent": float(agent_loss.detach().mean()),
            "q_tot_mean": float(masked_mean(q_tot.view(e, b, t), steps.mask).mean()),
            "lrp_conservation_gap": float(masked_mean(gap, steps.mask).mean()),
        }

    def state_dict(self) -> dict:
        return {
            **super().state_dict(),
            "target_epoch": self.clock.epoch,
            "reward_norm": self.reward_norm.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.clock.epoch = int(state["target_epoch"])
        self.reward_norm.load_state_dict(state["reward_norm"])
