"""Episode batches as torch tensors, and the network inputs built from them.

Shapes use E (ensemble members), B (episodes), T (transitions), N (agents), O (obs),
S (state), A (actions). Time-indexed inputs have T+1 steps (the last for bootstrapping).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import torch
from torch.nn import functional as F

from buffer_service.episode import EpisodeBatch
from learner.timers import timed


@dataclass(frozen=True)
class AgentInputLayout:
    """The agent network's per-agent input, the one definition of its parts and width:
    own observation, last action one-hot, agent id one-hot, concatenated in that order.

    Every builder of agent inputs (the learner's `agent_inputs`, the first-layer projection
    `networks.input_projection`, the acting `RolloutWorker`) and the network's input width
    (`networks.ActingSpec`) read it from here.

    Attributes:
        obs_dim: O, one agent's observation.
        n_actions: A, the last action one-hot.
        n_agents: N, the agent id one-hot.
    """

    obs_dim: int
    n_actions: int
    n_agents: int

    @property
    def parts(self) -> tuple[int, int, int]:
        """(O, A, N): widths of the observation, last-action and id parts, in input order."""
        return self.obs_dim, self.n_actions, self.n_agents

    @property
    def width(self) -> int:
        """O + A + N."""
        return sum(self.parts)


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
        with timed("batch"):
            return cls._convert(batch, device)

    @classmethod
    def _convert(cls, batch: EpisodeBatch, device: str | torch.device) -> TensorBatch:
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


_L1: dict[int, tuple] = {}  # id(obs) -> (weakref to obs, its version, its row norms)


def obs_l1(obs: torch.Tensor) -> torch.Tensor:
    """|obs|_1 of every observation, [E, B, T', N] (the agents' and RDN's critic's inputs both
    skip all-zero observations; computed once per observation tensor while it is unchanged)."""
    hit = _L1.get(id(obs))
    if hit is not None and hit[0]() is obs and hit[1] == obs._version:
        return hit[2]
    with torch.no_grad():
        norms = obs.abs().sum(-1)  # 10x cheaper than linalg.vector_norm(obs, 1, -1) on CPU
    remember_l1(obs, norms)
    return norms


def remember_l1(obs: torch.Tensor, norms: torch.Tensor) -> None:
    """Make `obs_l1(obs)` return `norms` while obs is alive and unchanged."""
    key = id(obs)
    _L1[key] = (weakref.ref(obs, lambda _: _L1.pop(key, None)), obs._version, norms)


def nonzero_obs(
    obs: torch.Tensor, order: tuple[int, int, int, int]
) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
    """The observations of obs [E, B, T', N, O] that are not all zero (dead agents and padding
    are), sorted by the axes of [E, B, T', N] taken in `order` (e.g. (0, 2, 1, 3): member,
    step, episode, agent): (rows [K, O], their (e, b, t, i) indices)."""
    with torch.no_grad():
        _, b, tp, n, o = obs.shape
        idx = (obs_l1(obs) > 0).permute(*order).nonzero()
        ei, bi, ti, ni = (idx[:, order.index(axis)] for axis in range(4))
        rows = obs.reshape(-1, o).index_select(0, ((ei * b + bi) * tp + ti) * n + ni)
    return rows, (ei, bi, ti, ni)


def agent_inputs(obs: torch.Tensor, actions: torch.Tensor, n_actions: int) -> AgentInputs:
    """Per-agent network inputs for every step: own obs, last action one-hot, id one-hot.

    Returned as `AgentInputs`, kept as its parts (`learner.networks.unroll` projects those;
    `.dense()` is `agent_inputs_dense`).

    Args:
        obs: [E, B, T', N, O] observations (T' steps).
        actions: [E, B, T, N] actions taken; the last action at step 0 is zeros, and so is
            it at steps past T + 1.
        n_actions: A.
    Returns:
        [E, B, T', N, O + A + N].
    """
    return AgentInputs(obs, actions, n_actions)


def agent_inputs_dense(obs: torch.Tensor, actions: torch.Tensor, n_actions: int) -> torch.Tensor:
    """`agent_inputs` as one dense tensor."""
    e, b, tp, n, _ = obs.shape
    last = torch.zeros(e, b, tp, n, n_actions, device=obs.device)
    k = min(tp - 1, actions.shape[2])
    if k > 0:
        last[:, :, 1 : k + 1] = F.one_hot(actions[:, :, :k], n_actions).float()
    ids = torch.eye(n, device=obs.device).expand(e, b, tp, n, n)
    return torch.cat([obs, last, ids], dim=-1)


class AgentInputs:
    """The agent network's inputs [E, B, T', N, O + A + N] kept as obs [E, B, T', N, O] and
    actions [E, B, T, N] (`agent_inputs`); `rows` and `onehot_index` are what a first layer
    needs to project them without building them (`networks.input_projection`)."""

    def __init__(self, obs: torch.Tensor, actions: torch.Tensor, a: int):
        e, b, tp, n, o = obs.shape
        self.shape = torch.Size((e, b, tp, n, AgentInputLayout(o, a, n).width))
        self.obs, self.actions, self.n_actions = obs, actions, a
        self._rows: dict[bool, tuple] = {}

    def dense(self) -> torch.Tensor:
        return agent_inputs_dense(self.obs, self.actions, self.n_actions)

    def rows(self, time_major: bool) -> tuple[torch.Tensor, list[int], torch.Tensor]:
        """The non-zero observations (all-zero ones, dead agents and padding, add nothing to
        a linear map): (rows [K, O] grouped by member, each member's count, each row's flat
        index in [E, T', B, N] (time_major) or [E, B, T', N])."""
        if time_major not in self._rows:
            e, b, tp, n, _ = self.obs.shape
            order = (0, 2, 1, 3) if time_major else (0, 1, 2, 3)
            rows, (ei, bi, ti, ni) = nonzero_obs(self.obs, order)  # sorted by member
            counts = torch.bincount(ei, minlength=e).tolist()
            flat = ((ei * tp + ti) * b + bi) if time_major else ((ei * b + bi) * tp + ti)
            self._rows[time_major] = (rows, counts, flat * n + ni)
        return self._rows[time_major]

    def onehot_index(self, time_major: bool) -> torch.Tensor:
        """Each input's row in a table [E*N*(A+1), .] of (member, agent, last action or "none"
        = A): (e*N + i)*(A+1) + the previous action, [E, T', B, N] or [E, B, T', N]."""
        e, b, tp, n, _ = self.obs.shape
        a = self.n_actions
        idx = torch.full((e, b, tp, n), a, dtype=torch.long, device=self.obs.device)
        k = min(tp - 1, self.actions.shape[2])
        if k > 0:
            idx[:, :, 1 : k + 1] = self.actions[:, :, :k]
        member = torch.arange(e, device=idx.device).view(e, 1, 1, 1)
        agent = torch.arange(n, device=idx.device).view(1, 1, 1, n)
        idx = (member * n + agent) * (a + 1) + idx
        return idx.transpose(1, 2) if time_major else idx


def joint_obs(obs: torch.Tensor) -> torch.Tensor:
    """[E, B, T', N, O] -> [E, B, T', N*O]: the joint observation (QMIX without state)."""
    return obs.flatten(-2)


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-member mean over the real entries: x, mask [E, ...] -> [E]."""
    return masked_part(x, mask, mask_count(mask))


def mask_count(mask: torch.Tensor) -> torch.Tensor:
    """Per-member count of real entries, at least 1: mask [E, ...] -> [E] (`masked_mean`'s
    denominator)."""
    return mask.sum(tuple(range(1, mask.dim()))).clamp_min(1.0)


def masked_part(x: torch.Tensor, mask: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
    """One pass's part of a per-member masked mean over a whole batch: the sum over this
    pass's real entries divided by the batch's `count` [E] (`mask_count` of the whole
    batch's mask). The parts of a batch's passes add up to its `masked_mean`
    (`learner.passes`). Shapes: x, mask [E, ...] -> [E]."""
    return (x * mask).sum(tuple(range(1, x.dim()))) / count


def greedy_actions(q: torch.Tensor, avail: torch.Tensor) -> torch.Tensor:
    """The best available action under q (ties: the lowest index), without gradient.

    Shapes: q, avail [..., A] -> [...] (long).
    """
    return q.detach().masked_fill(~avail, -1e10).argmax(-1)
