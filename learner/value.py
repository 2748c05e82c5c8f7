"""The value-decomposition family: IQL, VDN, QMIX and QMIX without state.

All four learn the shared DRQN agent by Q-learning on whole episodes; they differ only in
how the chosen agents' Q-values become the quantity regressed onto the TD target:
    iql     every agent on its own: Q_i -> r + γ max Q_i'
    vdn     Q_tot = Σ_i Q_i
    qmix    Q_tot = mixer(Q, state)           (hypernetworks conditioned on the state)
    qmix_ns Q_tot = mixer(Q, joint obs)       (the dissertation's "Qmix_NS": no state, same mixer)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

import torch

from buffer_service.episode import EpisodeBatch, EpisodeSchema
from learner.batch import (
    TensorBatch,
    agent_inputs,
    greedy_actions,
    joint_obs,
    mask_count,
    masked_part,
)
from learner.common import (
    AgentConfig,
    EpisodeClock,
    RewardNorm,
    TargetNet,
    Updater,
    validate_value_schedule,
)
from learner.networks import QMixer, VersionedWeights, unroll
from learner.passes import UPDATE_PASS_ROWS, episode_passes, validate_pass_rows
from learner.targets import q_lambda_targets

Mixing = Literal["none", "sum", "qmix", "qmix_ns"]


@dataclass(frozen=True)
class ValueConfig:
    """Hyper-parameters of IQL, VDN, QMIX and QMIX-nostate (seed 5.3.3 / SMAC paper).

    Attributes:
        gamma: discount.
        lr: learning rate.
        grad_norm_clip: per-seed gradient norm clip.
        target_update_episodes: inserted episodes between hard target-network copies
            (counted in episodes, so independent of actors, num_envs and the update rate;
            PyMARL's 200).
        optimiser: "adam" or "rmsprop" (PyMARL's α 0.99, ε 1e-5).
        reward_norm: "none", "scale" (divide by the running std) or "standardise" (also
            subtract the running mean; EPyMARL's standardise_rewards).
        td_lambda: λ of the Q(λ) targets built from the target network (0: one-step TD).
        double_q: pick the next action with the online network, evaluate with the target.
        mixer_embed: QMIX mixing embedding (qmix, qmix_ns only).
        hypernet_hidden: hidden width of QMIX's hypernetworks (qmix, qmix_ns only).
        update_pass_rows: the most agent-steps (members x episodes x steps x agents, padding
            included) one forward and backward pass of an update holds; a bigger batch goes
            through in passes of episodes of similar length whose gradients add up to the
            batch's (`learner.passes`: the same update up to float rounding, with a bounded
            working set and less padding). 0: the whole batch in one pass.
        agent: the shared agent network.
    """

    gamma: float = 0.99
    lr: float = 5e-4
    grad_norm_clip: float = 10.0
    target_update_episodes: int = 200
    optimiser: Literal["adam", "rmsprop"] = "adam"
    reward_norm: Literal["none", "scale", "standardise"] = "none"
    td_lambda: float = 0.0
    double_q: bool = True
    mixer_embed: int = 32
    hypernet_hidden: int = 64
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
        if self.mixer_embed < 1 or self.hypernet_hidden < 1:
            raise ValueError("mixer_embed and hypernet_hidden must be >= 1")
        validate_pass_rows(self.update_pass_rows)


class ValueLearner:
    """Q-learning with an optional mixer; see the module docstring.

    Calling loop::

        learner = ValueLearner(cfg, schema, mixing="sum", n_ensemble=1)
        metrics = learner.step(batch)          # batch: EpisodeBatch [B, ...] or [E, B, ...]
        weights = learner.get_weights()        # for the actors
    """

    policy_kind = "q"

    def __init__(
        self,
        cfg: ValueConfig,
        info: EpisodeSchema,
        mixing: Mixing,
        n_ensemble: int = 1,
        device: str = "cpu",
    ):
        self.cfg, self.info, self.mixing = cfg, info, mixing
        self.n_ensemble, self.device = n_ensemble, device
        self.acting = cfg.agent.acting_spec(info, self.policy_kind)
        self.agent = self.acting.build(n_ensemble).to(device)
        modules = [self.agent]
        self.mixer: QMixer | None = None
        if mixing in ("qmix", "qmix_ns"):
            cond = info.state_dim if mixing == "qmix" else info.n_agents * info.obs_dim
            self.mixer = QMixer(
                n_ensemble, info.n_agents, cond, cfg.mixer_embed, cfg.hypernet_hidden
            ).to(device)
            modules.append(self.mixer)
        self.target_agent = TargetNet(self.agent, cfg.target_update_episodes)
        self.target_mixer = (
            TargetNet(self.mixer, cfg.target_update_episodes) if self.mixer else None
        )
        self.clock = EpisodeClock(cfg.target_update_episodes)
        self.reward_norm = RewardNorm(cfg.reward_norm, n_ensemble, device)
        params = [p for m in modules for p in m.parameters()]
        self.updater = Updater(params, cfg.lr, cfg.grad_norm_clip, f"{mixing} TD", cfg.optimiser)
        self.updates = 0

    def sync_targets(self, episodes: int) -> bool:
        """Copy the online networks into the targets when `episodes` (inserted so far) has
        crossed another multiple of target_update_episodes; returns whether it did."""
        if not self.clock.due(episodes):
            return False
        self.target_agent.copy_now()
        if self.target_mixer:
            self.target_mixer.copy_now()
        return True

    def _cond(self, tb: TensorBatch) -> torch.Tensor:
        return tb.state if self.mixing == "qmix" else joint_obs(tb.obs)

    def _mix(self, mixer: QMixer | None, qs: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """qs [E, B, T, N] -> [E, B, T] (sum for VDN, mixer for QMIX)."""
        if self.mixing == "sum":
            return qs.sum(-1)
        e, b, t, n = qs.shape
        assert mixer is not None
        return mixer(qs.reshape(e, b * t, n), cond.reshape(e, b * t, -1)).view(e, b, t)

    def step(self, batch: EpisodeBatch, extra: EpisodeBatch | None = None) -> dict[str, float]:
        """One Q-learning update on a batch of episodes (`extra` is unused); returns metrics.

        The batch goes through in passes of at most `update_pass_rows` agent-steps
        (`learner.passes`), whose gradients add up to the whole batch's before one clip and
        optimiser step."""
        tb = TensorBatch.from_episodes(batch, self.device)
        tb = dataclasses.replace(tb, reward=self.reward_norm(tb.reward, tb.mask))
        steps = mask_count(tb.mask)
        count = steps
        if self.mixing == "none":  # every agent's TD error is an entry of the mean
            count = mask_count(tb.mask.unsqueeze(-1).expand(*tb.shape))
        self.updater.zero_grad()
        loss, q_taken = torch.zeros_like(count), torch.zeros_like(count)
        for part in episode_passes(tb, self.cfg.update_pass_rows):
            loss_part, q_part = self._pass(part, count, steps)
            self.updater.backward(loss_part)
            loss, q_taken = loss + loss_part.detach(), q_taken + q_part
            del part, loss_part  # before the next pass is built
        norms = self.updater.step()
        self.updates += 1
        return {
            "loss_td": float(loss.mean()),
            "q_taken_mean": float(q_taken.mean()),
            "grad_norm": float(norms.mean()),
        }

    def _pass(
        self, tb: TensorBatch, count: torch.Tensor, steps: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One pass's part of the TD loss ([E], with gradient) and of the mean Q-value of the
        taken actions ([E]), as shares of the whole batch's `count` of loss entries and its
        `steps` (`masked_part`); tb's rewards are already normalised."""
        inputs = agent_inputs(tb.obs, tb.actions, self.info.n_actions)
        qs = unroll(self.agent, inputs)  # [E, B, T+1, N, A]
        chosen = qs[:, :, :-1].gather(-1, tb.actions.unsqueeze(-1)).squeeze(-1)  # [E, B, T, N]
        with torch.no_grad():
            tqs = unroll(self.target_agent.module, inputs)[:, :, 1:]
            avail_next = tb.avail[:, :, 1:]
            if self.cfg.double_q:
                best = greedy_actions(qs[:, :, 1:], avail_next)
                next_q = tqs.gather(-1, best.unsqueeze(-1)).squeeze(-1)
            else:
                next_q = tqs.masked_fill(~avail_next, -1e10).max(-1).values
        cfg = self.cfg
        if self.mixing == "none":
            # per agent: put the agent axis before time for the target recursion
            y = q_lambda_targets(
                tb.reward.unsqueeze(-2).expand_as(next_q.transpose(-1, -2)),
                tb.terminated.unsqueeze(-2).expand_as(next_q.transpose(-1, -2)),
                tb.mask.unsqueeze(-2).expand_as(next_q.transpose(-1, -2)),
                next_q.transpose(-1, -2),
                cfg.gamma,
                cfg.td_lambda,
            ).transpose(-1, -2)
            td = chosen - y
            loss = masked_part(td.pow(2), tb.mask.unsqueeze(-1).expand_as(td), count)
            q_taken = chosen.mean(-1)
        else:
            cond = self._cond(tb)
            q_tot = self._mix(self.mixer, chosen, cond[:, :, :-1])
            with torch.no_grad():
                target_mixer = self.target_mixer.module if self.target_mixer else None
                next_tot = self._mix(target_mixer, next_q, cond[:, :, 1:])
                y = q_lambda_targets(
                    tb.reward, tb.terminated, tb.mask, next_tot, cfg.gamma, cfg.td_lambda
                )
            td = q_tot - y
            loss = masked_part(td.pow(2), tb.mask, count)
            q_taken = q_tot
        return loss, masked_part(q_taken.detach(), tb.mask, steps)

    def get_weights(self) -> VersionedWeights:
        return VersionedWeights.from_module(self.agent, self.updates)

    def state_dict(self) -> dict:
        return {
            "agent": self.agent.state_dict(),
            "mixer": self.mixer.state_dict() if self.mixer else None,
            "target_agent": self.target_agent.module.state_dict(),
            "target_mixer": self.target_mixer.module.state_dict() if self.target_mixer else None,
            "optimiser": self.updater.optimiser.state_dict(),
            "updates": self.updates,
            "target_epoch": self.clock.epoch,
            "reward_norm": self.reward_norm.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.agent.load_state_dict(state["agent"])
        self.target_agent.module.load_state_dict(state["target_agent"])
        if self.mixer is not None:
            self.mixer.load_state_dict(state["mixer"])
            self.target_mixer.module.load_state_dict(state["target_mixer"])
        self.updater.optimiser.load_state_dict(state["optimiser"])
        self.updates = int(state["updates"])
        self.clock.epoch = int(state["target_epoch"])
        self.reward_norm.load_state_dict(state["reward_norm"])
