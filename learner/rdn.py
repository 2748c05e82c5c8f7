"""RDN, the Relevance Decomposition Network (Singh, "Improving central value functions for
cooperative multi-agent reinforcement learning", MSc dissertation, University of the
Witwatersrand, 2022; chapter 4, Algorithm 1).

A central critic Q_c(x) over every agent's last `obs_window` observations, current action
one-hot and id one-hot is trained by TD. Its value for the taken joint action is split into
per-agent targets by LRP-epsilon: agent i's target is the relevance summed over its own input
block, and each agent's Q_i(o_i, u_i) is regressed onto it. The state is never used.

`learner.rdn_reference` is the same update written out densely, top to bottom: read it for the
method. `RDNLearner.step` below computes the same numbers on structured critic inputs
(`learner.critic_inputs`) with its agents' targets from `learner.rdn_fast.agent_targets`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

import torch

from buffer_service.episode import EpisodeBatch, EpisodeSchema
from learner.batch import TensorBatch, agent_inputs, greedy_actions, mask_count, masked_part
from learner.common import (
    AgentConfig,
    AgentCriticLearner,
    EpisodeClock,
    RewardNorm,
    TargetNet,
    Updater,
    validate_value_schedule,
)
from learner.critic_inputs import AgentBlocks, AllSteps, RealSteps, agent_blocks
from learner.networks import MLP, AgentBlockLinear, unroll
from learner.passes import UPDATE_PASS_ROWS, episode_passes, validate_pass_rows
from learner.precision import float32_only
from learner.rdn_fast import agent_targets
from learner.targets import q_lambda_targets


@dataclass(frozen=True)
class RDNConfig:
    """Hyper-parameters of RDN (the dissertation's 5.3.3).

    Attributes:
        gamma: discount.
        lr: learning rate of the critic (and of the agents, times agent_lr_scale).
        agent_lr_scale: the agents' learning rate as a multiple of lr (1: the dissertation's
            one rate).
        grad_norm_clip: per-member gradient norm clip.
        target_update_episodes: inserted episodes between hard copies into the target critic
            (as the value family's).
        optimiser: "adam" or "rmsprop".
        reward_norm: "none", "scale" or "standardise" (as the value family's).
        td_lambda: lambda of the critic's Q(lambda) targets (0: one-step TD).
        critic_hidden: hidden widths of the central critic MLP.
        critic_agent_encoder: 0 (the dissertation's critic: the MLP acts on the concatenated
            blocks) or the width H of a first layer shared by every agent's block
            (`AgentBlockLinear`: agent i's block -> its own H units, the same weights for all
            agents), before the `critic_hidden` layers. Still a ReLU MLP over the same input,
            so LRP is unchanged.
        obs_window: how many of each agent's latest observations the critic sees.
        lrp_eps: epsilon of the LRP-epsilon rule (`learner.rdn_reference.epsilon_rule`).
        agent_targets: "taken" (the dissertation's: Q_i(o_i, u_i) of the taken action
            regresses onto agent i's LRP share of Q_c(x)) or "counterfactual" (the taken
            action's target is its LRP share; every other available action a gets that share
            plus the critic's own difference Q_c(x with agent i's action a) - Q_c(x), so the
            agent's action ranking is the critic's and its level is its LRP credit).
        update_pass_rows: the most agent-steps one forward and backward pass of an update
            holds; a bigger batch goes through in passes (`learner.passes`; the same update
            up to float rounding; 0: one pass). As the value family's.
        agent: the shared agent network.

    The critic's TD target bootstraps at the agents' greedy next joint action, and the agents'
    targets are split from the online critic just updated, at the taken joint action. Other
    variants (next_action local_max/joint_max, lrp_reference no_actions, split_critic target,
    split_actions greedy, agent_targets all_actions, the LRP rules eps, eps_nobias and
    grad_x_input) were measured and left unused by every shipped layer; commit 828260c has them.
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
    lrp_eps: float = 0.01
    agent_targets: Literal["taken", "counterfactual"] = "taken"
    update_pass_rows: int = UPDATE_PASS_ROWS
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
        if self.lrp_eps <= 0:
            raise ValueError(f"lrp_eps must be > 0, got {self.lrp_eps}")
        if self.critic_agent_encoder < 0:
            raise ValueError(f"critic_agent_encoder must be >= 0, got {self.critic_agent_encoder}")
        if self.obs_window < 1:
            raise ValueError(f"obs_window must be >= 1, got {self.obs_window}")
        if not self.critic_hidden or min(self.critic_hidden) < 1:
            raise ValueError(
                f"critic_hidden needs at least one positive width, got {self.critic_hidden}"
            )
        validate_pass_rows(self.update_pass_rows)


# Keys an RDNConfig had until commit 828260c, with the one value the code still computes (None:
# any value; it only bounded a retired variant). A saved config.yaml that holds them resumes.
RETIRED_KEYS = {
    "next_action": "greedy",
    "split_critic": "online",
    "split_actions": "taken",
    "lrp_reference": "zero",
    "lrp_rule": "eps_residual",
    "joint_max_limit": None,
}


def drop_retired_keys(algo: dict) -> dict:
    """`algo` (an RDN config section) without the retired keys that hold what RDN computes.

    Raises:
        ValueError: a retired key holds a variant that is gone; the message names it and the
            commit that had it.
    """
    for key, kept in RETIRED_KEYS.items():
        if key in algo and kept is not None and algo[key] != kept:
            raise ValueError(
                f"algo.{key}={algo[key]!r} is a retired RDN variant (commit 828260c has it); "
                f"RDN now always computes {key}={kept!r}"
            )
    return {k: v for k, v in algo.items() if k not in RETIRED_KEYS}


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

    def sync_targets(self, episodes: int) -> bool:
        """Copy the critic into the target critic every target_update_episodes episodes."""
        if not self.clock.due(episodes):
            return False
        self.target_critic.copy_now()
        return True

    def critic_inputs(self, hist, actions: torch.Tensor):
        """Per-agent blocks [history, action one-hot, id one-hot] laid end to end
        (`learner.critic_inputs.agent_blocks`: kept as its parts when hist is a window view, so
        the critic and LRP multiply each observation once; dense otherwise, the same values).

        Shapes: hist [E, B, T', N, W*O], actions [E, B, T', N] -> [E, B*T', N*block].
        """
        return agent_blocks(hist, actions, self.info.n_actions, self.cfg.obs_window)

    def shares(self, hist, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each agent's LRP share of the critic's value at the critic input of `hist` and
        `actions` (as `critic_inputs`): (shares [E, M, N], Q_c [E, M]); for inspection."""
        x = self.critic_inputs(hist, actions)
        e, n = actions.shape[0], self.info.n_agents
        offset = self.cfg.obs_window * self.info.obs_dim
        out = agent_targets(
            self.critic, x, actions.reshape(e, -1, n), None, self.cfg.lrp_eps, offset
        )
        return out.shares, out.q

    def critic_steps(self, tb: TensorBatch) -> AllSteps | RealSteps:
        """The critic's layout of the batch's steps: the real steps packed together when the
        critic sees one observation per agent (`RealSteps`, the same values without computing
        anything for padding), else every step (`AllSteps`)."""
        if self.cfg.obs_window == 1:
            return RealSteps(tb)
        return AllSteps(tb, self.cfg.obs_window)

    def step(self, batch: EpisodeBatch, extra: EpisodeBatch | None = None) -> dict[str, float]:
        """One RDN update (critic, then agents; `extra` is unused); returns scalar metrics.
        `learner.rdn_reference.reference_update` is the same update, dense.

        The critic side runs on `self.critic_steps(tb)`'s layout, [E, B', T', ...]: every
        step, or the real steps packed; the agents' Q-values are taken into it, and the next
        values put back for the Q(lambda) targets, which need the episodes' time order.

        A batch of more than `update_pass_rows` agent-steps goes through in passes
        (`learner.passes`): the critic's loss pass by pass, one critic step, then the agents'
        loss pass by pass against the updated critic, one agent step. The agents are unrolled
        twice then (without a graph for the critic's greedy next actions, with one for their
        own loss), so that no pass keeps its graph while another is computed."""
        tb = TensorBatch.from_episodes(batch, self.device)
        tb = dataclasses.replace(tb, reward=self.reward_norm(tb.reward, tb.mask))
        passes = episode_passes(tb, self.cfg.update_pass_rows)
        counts = self._counts(tb)
        parts = []
        self.critic_updater.zero_grad()
        if len(passes) == 1:  # one unroll: its graph serves the agents' loss below
            steps, qs_all = self.critic_steps(tb), self._unroll(tb)
            x, metrics = self._critic_pass(tb, steps, qs_all.detach(), counts)
            parts.append(metrics)
        else:
            for part in passes:
                with torch.no_grad():
                    qs_part = self._unroll(part)
                parts.append(self._critic_pass(part, self.critic_steps(part), qs_part, counts)[1])
                del part, qs_part  # before the next pass is built
        self.critic_updater.step()
        self.agent_updater.zero_grad()
        if len(passes) == 1:
            parts.append(self._agent_pass(tb, steps, x, qs_all, counts))
        else:
            for part in passes:
                steps = self.critic_steps(part)
                parts.append(self._agent_pass(part, steps, None, self._unroll(part), counts))
                del part, steps
        self.agent_updater.step()
        self.updates += 1
        total: dict[str, torch.Tensor] = {}
        for metrics in parts:
            for key, value in metrics.items():
                total[key] = total[key] + value if key in total else value
        return {key: float(value.mean()) for key, value in total.items()}

    def _unroll(self, tb: TensorBatch) -> torch.Tensor:
        """The agents' Q-values [E, B, T+1, N, A], float32 (under run.precision=bf16 only the
        agents' unroll runs in bfloat16: the critic's layers are float32 only; the cast is
        exact)."""
        qs = unroll(self.agent, agent_inputs(tb.obs, tb.actions, self.info.n_actions))
        return qs.float()

    def _counts(self, tb: TensorBatch) -> dict[str, torch.Tensor]:
        """The whole batch's denominators of the update's masked means, [E] each: its real
        steps, its agent-steps, and (counterfactual targets) its available actions at them."""
        counts = {
            "steps": mask_count(tb.mask),
            "agent_steps": mask_count(tb.mask.unsqueeze(-1).expand(*tb.shape)),
        }
        if self.cfg.agent_targets == "counterfactual":
            ok = tb.avail[:, :, : tb.shape[2]] & tb.mask.bool()[..., None, None]
            counts["actions"] = mask_count(ok.float())
        return counts

    def _critic_pass(
        self,
        tb: TensorBatch,
        steps: AllSteps | RealSteps,
        qs_all: torch.Tensor,
        counts: dict[str, torch.Tensor],
    ) -> tuple[AgentBlocks | torch.Tensor, dict[str, torch.Tensor]]:
        """Backpropagate this pass's part of the critic's TD loss (qs_all: the agents'
        Q-values, without gradient; tb's rewards already normalised); returns the critic's
        input and this pass's part of the loss metric."""
        actions = steps.take(tb.actions)
        e, b, t = steps.mask.shape
        with float32_only(qs_all.device):
            x = self.critic_inputs(steps.hist(), actions)
            with torch.no_grad():
                greedy = greedy_actions(steps.take(qs_all, 1), steps.take(tb.avail, 1))
                x_next = self.critic_inputs(steps.hist(1), greedy)
                v_next = steps.put(self.target_critic.module(x_next).view(e, b, t))  # [E, B, T]
                y = q_lambda_targets(
                    tb.reward, tb.terminated, tb.mask, v_next, self.cfg.gamma, self.cfg.td_lambda
                )
                y = steps.take(y)
            q_c = self.critic(x).view(e, b, t)
            loss = masked_part((q_c - y).pow(2), steps.mask, counts["steps"])
            self.critic_updater.backward(loss)
        return x, {"loss_critic": loss.detach()}

    def _agent_pass(
        self,
        tb: TensorBatch,
        steps: AllSteps | RealSteps,
        x: AgentBlocks | torch.Tensor | None,
        qs_all: torch.Tensor,
        counts: dict[str, torch.Tensor],
    ) -> dict[str, torch.Tensor]:
        """Backpropagate this pass's part of the agents' loss toward the (updated) critic's
        LRP shares at its input x (None: built here); qs_all: the agents' Q-values with their
        graph. Returns this pass's parts of the metrics."""
        n, a = self.info.n_agents, self.info.n_actions
        qs, actions, avail = steps.take(qs_all), steps.take(tb.actions), steps.take(tb.avail)
        e, b, t = steps.mask.shape
        counterfactual = self.cfg.agent_targets == "counterfactual"
        ok = avail & steps.mask.bool()[..., None, None]  # the entries the agents' loss uses
        keep = ok.view(e, b * t, n, a) if counterfactual else None
        offset = self.cfg.obs_window * self.info.obs_dim
        with float32_only(qs_all.device):
            if x is None:
                x = self.critic_inputs(steps.hist(), actions)
            shares, q_tot, every = agent_targets(
                self.critic, x, actions.view(e, b * t, n), keep, self.cfg.lrp_eps, offset
            )
            shares = shares.view(e, b, t, n)
            if not counterfactual:
                chosen = qs.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
                mask = steps.mask.unsqueeze(-1).expand_as(chosen)
                loss = masked_part((chosen - shares).pow(2), mask, counts["agent_steps"])
            else:  # a target for every available action of every agent
                target = every.view(e, b, t, n, a)
                loss = masked_part((qs - target).pow(2), ok.float(), counts["actions"])
            self.agent_updater.backward(loss)
        gap = (shares.sum(-1) - q_tot.view(e, b, t)).abs()
        return {
            "loss_agent": loss.detach(),
            "q_tot_mean": masked_part(q_tot.view(e, b, t), steps.mask, counts["steps"]),
            "lrp_conservation_gap": masked_part(gap, steps.mask, counts["steps"]),
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
