"""Episode batches as torch tensors, and the network inputs built from them.

Shapes use E (ensemble members), B (episodes), T (transitions), N (agents), O (obs),
S (state), A (actions). Time-indexed inputs have T+1 steps (the last for bootstrapping).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn import functional as F

from buffer_service.episode import EpisodeBatch


@dataclass(frozen=True)
class TensorBatch:
    """An EpisodeBatch on the learner's device, always with an ensemble axis.

    Shapes: obs [E, B, T+1, N, O]; state [E, B, T+1, S]; avail [E, B, T+1, N, A] bool;
    actions [E, B, T, N] long; reward, terminated, mask [E, B, T] float;
    policy_version [E, B] long.
    """

    obs: torch.Tensor
    state: torch.Tensor
    avail: torch.Tensor
    actions: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    mask: torch.Tensor
    policy_version: torch.Tensor

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """(E, B, T, N)."""
        e, b, t, n = self.actions.shape
        return e, b, t, n

    @classmethod
    def from_episodes(cls, batch: EpisodeBatch, device: str | torch.device = "cpu") -> TensorBatch:
        """Convert; a batch without an ensemble axis gets E = 1."""
        add_e = batch.reward.ndim == 2

        def t(arr, dtype):
            x = torch.as_tensor(arr, device=device).to(dtype)
            return x.unsqueeze(0) if add_e else x

        return cls(
            obs=t(batch.obs, torch.float32),
            state=t(batch.state, torch.float32),
            avail=t(batch.avail_actions, torch.bool),
            actions=t(batch.actions, torch.long),
            reward=t(batch.reward, torch.float32),
            terminated=t(batch.terminated, torch.float32),
            mask=t(batch.filled, torch.float32),
            policy_version=t(batch.policy_version, torch.long),
        )


def agent_inputs(obs: torch.Tensor, actions: torch.Tensor, n_actions: int) -> torch.Tensor:
    """Per-agent network inputs for every step: own obs, last action one-hot, id one-hot.

    Args:
        obs: [E, B, T', N, O] observations (T' steps).
        actions: [E, B, T, N] actions taken; the last action at step 0 is zeros, and steps
            past T use the last recorded action.
        n_actions: A.
    Returns:
        [E, B, T', N, O + A + N].
    """
    e, b, tp, n, _ = obs.shape
    last = torch.zeros(e, b, tp, n, n_actions, device=obs.device)
    k = min(tp - 1, actions.shape[2])
    if k > 0:
        last[:, :, 1 : k + 1] = F.one_hot(actions[:, :, :k], n_actions).float()
    ids = torch.eye(n, device=obs.device).expand(e, b, tp, n, n)
    return torch.cat([obs, last, ids], dim=-1)


def obs_history(obs: torch.Tensor, window: int) -> torch.Tensor:
    """Each step's last `window` observations, oldest first, zero before the episode start.

    Args:
        obs: [E, B, T', N, O].
    Returns:
        [E, B, T', N, window * O].
    """
    pad = obs.new_zeros(*obs.shape[:2], window - 1, *obs.shape[3:])
    padded = torch.cat([pad, obs], dim=2)
    tp = obs.shape[2]
    return torch.cat([padded[:, :, i : i + tp] for i in range(window)], dim=-1)


def joint_obs(obs: torch.Tensor) -> torch.Tensor:
    """[E, B, T', N, O] -> [E, B, T', N*O]: the joint observation (QMIX without state)."""
    return obs.flatten(-2)


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-member mean over the real entries: x, mask [E, ...] -> [E]."""
    dims = tuple(range(1, x.dim()))
    return (x * mask).sum(dims) / mask.sum(dims).clamp_min(1.0)
