"""Episode batches as torch tensors, and the network inputs built from them.

Shapes use E (ensemble members), B (episodes), T (transitions), N (agents), O (obs),
S (state), A (actions). Time-indexed inputs have T+1 steps (the last for bootstrapping).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn import functional as F

from buffer_service.episode import EpisodeBatch
from learner.lazy import LazyTensor


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

    The result is a read-only view (no copy of the windows): every agent's observations are
    laid out once, time-major after window - 1 zero steps, and window t is the `window * O`
    consecutive floats starting at step t, so consecutive windows overlap in memory (time
    stride O). Writing into it would change several windows at once; take `.clone()` (or
    `.contiguous()`) for a writable copy. `AgentBlocks` reads each observation once from it.

    Args:
        obs: [E, B, T', N, O].
    Returns:
        [E, B, T', N, window * O].
    """
    e, b, tp, n, o = obs.shape
    s = tp + window - 1
    series = obs.new_empty(e, b, n, s, o)
    series[:, :, :, : window - 1] = 0.0
    series[:, :, :, window - 1 :] = obs.transpose(2, 3)
    st = series.stride()
    return series.as_strided((e, b, tp, n, window * o), (st[0], st[1], o, st[2], 1))


def window_series(hist: torch.Tensor, window: int) -> torch.Tensor | None:
    """The observations behind a window view: series [E, B, T'+window-1, N, O] with
    hist[:, :, t, :, w*O:(w+1)*O] == series[:, :, t + w] for every t and w, or None when
    `hist` is not laid out as such a view.

    A tensor whose time stride equals O (and whose feature stride is 1) holds window t's slot
    w at the same address as window t+w's slot 0, whatever made it; `obs_history`'s result and
    its slices along time are such tensors, a dense [E, B, T', N, W*O] tensor is not.
    """
    e, b, tp, n, wo = hist.shape
    o = wo // window
    if hist.stride(4) != 1 or wo != window * o or (tp > 1 and hist.stride(2) != o):
        return None
    st = hist.stride()
    return hist.as_strided(
        (e, b, tp + window - 1, n, o), (st[0], st[1], o, st[3], 1), hist.storage_offset()
    )


class AgentBlocks(LazyTensor):
    """A central critic's input x [E, B*T', N*block] with block = [the agent's window of
    observations (W*O), its action one-hot (A), its id one-hot (N)], kept as its parts.

    `series` holds every observation once; `block_l1` and `alive_rows` are what the critic's
    first layer (`learner.networks.block_contributions`) and LRP's per-agent sums
    (`learner.lrp`) need. Any other torch operation sees the dense tensor (`agent_blocks_dense`,
    computed once on first use). Built by `agent_blocks`.
    """

    def __new__(cls, hist: torch.Tensor, series: torch.Tensor, actions: torch.Tensor, a: int):
        e, b, tp, n, wo = hist.shape
        return super().__new__(cls, (e, b * tp, n * (wo + a + n)), hist)

    def __init__(self, hist: torch.Tensor, series: torch.Tensor, actions: torch.Tensor, a: int):
        super().__init__(self.shape, hist)
        self.hist, self.series, self.actions, self.n_actions = hist, series, actions, a
        _, self.episodes, self.steps, self.n_agents, wo = hist.shape
        self.obs_dim = series.shape[-1]
        self.window = wo // self.obs_dim
        self.block = wo + a + self.n_agents
        self._rows: tuple | None = None
        self._l1: torch.Tensor | None = None

    def materialise(self) -> torch.Tensor:
        return agent_blocks_dense(self.hist, self.actions, self.n_actions)

    def series_l1(self) -> torch.Tensor:
        """|obs|_1 of every series row, [E, B, T'+W-1, N] (computed once)."""
        if self._l1 is None:
            with torch.no_grad():
                self._l1 = torch.linalg.vector_norm(self.series, 1, -1)
        return self._l1

    def block_l1(self) -> torch.Tensor:
        """Σ_j |x_j| over each agent's block, [E, B*T', N]: its window's observations plus 1
        for the action one-hot and 1 for the id one-hot."""
        l1, tp = self.series_l1(), self.steps
        window_l1 = sum(l1[:, :, k : k + tp] for k in range(self.window))
        return (window_l1 + 2.0).reshape(l1.shape[0], -1, self.n_agents)

    def alive_rows(self) -> tuple[torch.Tensor, list[int], list[tuple[torch.Tensor, torch.Tensor]]]:
        """The non-zero observations, grouped by (member, agent): (rows [K, O], the number of
        rows of each (e, i) group in e-major order, and per window slot w the pairs (which of
        the K rows, flat index (e, b, t, i) of the window [E*B*T'*N] it fills slot w of)).
        An all-zero observation (a dead agent, padding, before the start) adds nothing to any
        linear map of x, so only these rows are multiplied."""
        if self._rows is None:
            with torch.no_grad():
                self._rows = self._find_rows()
        return self._rows

    def _find_rows(self) -> tuple:
        e, b, _, n = self.series_l1().shape
        idx = (self.series_l1() > 0).permute(0, 3, 1, 2).nonzero()  # sorted by (e, i, b, s)
        ei, ni, bi, si = idx.unbind(1)
        counts = torch.bincount(ei * n + ni, minlength=e * n).tolist()
        rows = self.series[ei, bi, si, ni]
        slots = []
        for w in range(self.window):
            t = si - w
            ok = ((t >= 0) & (t < self.steps)).nonzero().squeeze(1)
            flat = ((ei[ok] * b + bi[ok]) * self.steps + t[ok]) * n + ni[ok]
            slots.append((ok, flat))
        return rows, counts, slots


def agent_blocks_dense(hist: torch.Tensor, actions: torch.Tensor, n_actions: int) -> torch.Tensor:
    """Per-agent blocks [history, action one-hot, id one-hot] laid end to end, as one tensor.

    Shapes: hist [E, B, T', N, W*O], actions [E, B, T', N] -> [E, B*T', N*block].
    """
    e, b, tp, n, _ = hist.shape
    ids = torch.eye(n, device=hist.device).expand(e, b, tp, n, n)
    x = torch.cat([hist, F.one_hot(actions, n_actions).float(), ids], dim=-1)
    return x.reshape(e, b * tp, -1)


def agent_blocks(
    hist: torch.Tensor, actions: torch.Tensor, n_actions: int, window: int
) -> torch.Tensor:
    """The critic input of `agent_blocks_dense`: lazily as `AgentBlocks` when `hist` is a
    window view (`obs_history` and its time slices), else dense. Both hold the same values.

    Shapes: hist [E, B, T', N, W*O], actions [E, B, T', N] -> [E, B*T', N*block].
    """
    series = window_series(hist, window)
    if series is None:
        return agent_blocks_dense(hist, actions, n_actions)
    return AgentBlocks(hist, series, actions, n_actions)


def joint_obs(obs: torch.Tensor) -> torch.Tensor:
    """[E, B, T', N, O] -> [E, B, T', N*O]: the joint observation (QMIX without state)."""
    return obs.flatten(-2)


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-member mean over the real entries: x, mask [E, ...] -> [E]."""
    dims = tuple(range(1, x.dim()))
    return (x * mask).sum(dims) / mask.sum(dims).clamp_min(1.0)
