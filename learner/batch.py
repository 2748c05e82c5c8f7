"""Episode batches as torch tensors, and the network inputs built from them.

Shapes use E (ensemble members), B (episodes), T (transitions), N (agents), O (obs),
S (state), A (actions). Time-indexed inputs have T+1 steps (the last for bootstrapping).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any

import torch
from torch.nn import functional as F

from buffer_service.episode import EpisodeBatch
from learner.lazy import LazyTensor


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
    _remember_l1(obs, norms)
    return norms


def _remember_l1(obs: torch.Tensor, norms: torch.Tensor) -> None:
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


def agent_inputs(obs: torch.Tensor, actions: torch.Tensor, n_actions: int) -> torch.Tensor:
    """Per-agent network inputs for every step: own obs, last action one-hot, id one-hot.

    Returned as `AgentInputs` (the values are computed only when an operation needs them;
    `learner.networks.unroll` projects the parts instead).

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


class AgentInputs(LazyTensor):
    """The agent network's inputs [E, B, T', N, O + A + N] kept as obs [E, B, T', N, O] and
    actions [E, B, T, N] (`agent_inputs`); `rows` and `last_action_index` are what a
    first layer needs to project them without building them (`networks.input_projection`)."""

    def __new__(cls, obs: torch.Tensor, actions: torch.Tensor, a: int):
        e, b, tp, n, o = obs.shape
        return super().__new__(cls, (e, b, tp, n, AgentInputLayout(o, a, n).width), obs)

    def __init__(self, obs: torch.Tensor, actions: torch.Tensor, a: int):
        super().__init__(tuple(self.shape), obs)
        self.obs, self.actions, self.n_actions = obs, actions, a
        self._rows: dict[bool, tuple] = {}

    def materialise(self) -> torch.Tensor:
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


def obs_history(obs: torch.Tensor, window: int) -> torch.Tensor:
    """Each step's last `window` observations, oldest first, zero before the episode start.

    Returned as `ObsWindows`, which keeps `obs` and computes the windows only when an
    operation needs them (its slices along time stay lazy); `AgentBlocks` reads the
    observations from it directly.

    Args:
        obs: [E, B, T', N, O].
    Returns:
        [E, B, T', N, window * O].
    """
    return ObsWindows(obs, window)


def obs_windows_dense(obs: torch.Tensor, window: int) -> torch.Tensor:
    """`obs_history` as one dense tensor [E, B, T', N, window * O]."""
    pad = obs.new_zeros(*obs.shape[:2], window - 1, *obs.shape[3:])
    padded = torch.cat([pad, obs], dim=2)
    tp = obs.shape[2]
    return torch.cat([padded[:, :, i : i + tp] for i in range(window)], dim=-1)


class ObsWindows(LazyTensor):
    """The windows of `obs_history` for steps start .. start+steps-1 of obs, [E, B, steps, N,
    window * O], kept as obs (read-only). Slicing along time gives another ObsWindows of the
    same obs; anything else sees the dense windows."""

    def __new__(cls, obs: torch.Tensor, window: int, start: int = 0, steps: int | None = None):
        e, b, tp, n, o = obs.shape
        steps = tp - start if steps is None else steps
        return super().__new__(cls, (e, b, steps, n, window * o), obs)

    def __init__(self, obs: torch.Tensor, window: int, start: int = 0, steps: int | None = None):
        super().__init__(tuple(self.shape), obs)
        self.obs, self.window, self.start, self.steps = obs, window, start, self.shape[2]
        self._norms: list[torch.Tensor] = []  # shared by every slice of the same windows
        self._alive: list[tuple] = []  # likewise

    def materialise(self) -> torch.Tensor:
        stop = self.start + self.steps
        return obs_windows_dense(self.obs[:, :, :stop], self.window)[:, :, self.start :]

    def structured(self, func: Any, args: tuple, kwargs: dict) -> Any:
        if func is not torch.ops.aten.slice.Tensor or kwargs:
            return NotImplemented
        dim, lo, hi, step = (list(args[1:]) + [0, None, None, 1][len(args) - 1 :])[:4]
        if dim not in (2, -3) or step != 1:
            return NotImplemented
        lo, hi, _ = slice(lo, hi).indices(self.steps)
        part = ObsWindows(self.obs, self.window, self.start + lo, max(hi - lo, 0))
        part._norms, part._alive = self._norms, self._alive
        return part

    def padded_l1(self) -> torch.Tensor:
        """|obs|_1 per (e, b, step, i) after window - 1 zero steps, [E, B, W-1+T_obs, N]
        (computed once for all slices)."""
        if not self._norms:
            with torch.no_grad():
                l1 = obs_l1(self.obs)
                pad = l1.new_zeros(*l1.shape[:2], self.window - 1, l1.shape[-1])
                self._norms.append(torch.cat([pad, l1], dim=2))
        return self._norms[0]

    def alive_obs(self) -> tuple[torch.Tensor, list[int], tuple[torch.Tensor, ...]]:
        """Every non-zero observation of obs, whichever windows it falls in (computed once for
        all slices): (rows [K, O] sorted by (member, agent, episode, step); the number of rows
        of each (e, i), e-major; their (e, i, b, step) indices)."""
        if not self._alive:
            e, n = self.obs.shape[0], self.obs.shape[3]
            rows, (ei, bi, ui, ni) = nonzero_obs(self.obs, (0, 3, 1, 2))
            counts = torch.bincount(ei * n + ni, minlength=e * n).tolist()
            self._alive.append((rows, counts, (ei, ni, bi, ui)))
        return self._alive[0]


class AgentBlocks(LazyTensor):
    """A central critic's input x [E, B*T', N*block] with block = [the agent's window of
    observations (W*O), its action one-hot (A), its id one-hot (N)], kept as its parts: the
    windows (an `ObsWindows`), the actions and A.

    `block_l1`, `alive_rows` and `action_index` are what the critic's first layer
    (`learner.networks.block_preactivation`) and LRP's per-agent sums (`learner.lrp`,
    `learner.networks.block_dot`) need. Any other torch operation sees the dense tensor
    (`agent_blocks_dense`, computed once on first use). Built by `agent_blocks`.

    Series index s (0 .. T'+W-2) is observation step hist.start + s - (W-1): window t holds
    series rows t .. t+W-1.
    """

    def __new__(cls, hist: ObsWindows, actions: torch.Tensor, a: int):
        e, b, tp, n, wo = hist.shape
        return super().__new__(cls, (e, b * tp, n * (wo + a + n)), hist)

    def __init__(self, hist: ObsWindows, actions: torch.Tensor, a: int):
        super().__init__(tuple(self.shape), hist)
        self.hist, self.actions, self.n_actions = hist, actions, a
        _, self.episodes, self.steps, self.n_agents, wo = hist.shape
        self.obs_dim, self.window = hist.obs.shape[-1], hist.window
        self.block = wo + a + self.n_agents
        self._rows: tuple | None = None

    def materialise(self) -> torch.Tensor:
        return agent_blocks_dense(self.hist, self.actions, self.n_actions)

    def series_l1(self) -> torch.Tensor:
        """|obs|_1 of every series row, [E, B, T'+W-1, N] (zero before the episode start)."""
        return self.hist.padded_l1()[:, :, self.hist.start : self.hist.start + self.span_rows]

    @property
    def span_rows(self) -> int:
        return self.steps + self.window - 1

    def block_l1(self) -> torch.Tensor:
        """Σ_j |x_j| over each agent's block, [E, B*T', N]: its window's observations plus 1
        for the action one-hot and 1 for the id one-hot."""
        l1, tp = self.series_l1(), self.steps
        window_l1 = sum(l1[:, :, k : k + tp] for k in range(self.window))
        return (window_l1 + 2.0).reshape(l1.shape[0], -1, self.n_agents)

    def alive_rows(self) -> tuple[torch.Tensor, list[int], torch.Tensor, torch.Tensor]:
        """The non-zero observations, grouped by (member, agent), and the windows they fill.

        Returns (rows [K, O] (`ObsWindows.alive_obs`, shared by every slice of the same
        windows); the number of rows of each (e, i) group, e-major; for each row and window
        slot w, [K, W], the flat index of the window it fills in a buffer [E, B, T', N] and in
        one [E, B, T'] summed over agents, or the buffer's size (one extra row, never read)
        where that window is outside these T' steps). An all-zero observation (a dead agent,
        padding, before the episode start) adds nothing to a linear map of x, so only these
        rows are multiplied."""
        if self._rows is None:
            with torch.no_grad():
                self._rows = self._find_rows()
        return self._rows

    def action_index(self) -> torch.Tensor:
        """Each (e, row, i)'s row in the first layer's action weights seen as [E*N*A, H]:
        (e*N + i)*A + action, [E, B*T', N]."""
        e, n, a = self.actions.shape[0], self.n_agents, self.n_actions
        member = torch.arange(e, device=self.actions.device).view(e, 1, 1, 1)
        agent = torch.arange(n, device=self.actions.device).view(1, 1, 1, n)
        return ((member * n + agent) * a + self.actions).view(e, -1, n)

    def _find_rows(self) -> tuple:
        rows, counts, (ei, ni, bi, ui) = self.hist.alive_obs()
        w, n, steps = self.window, self.n_agents, self.steps
        # observation step u sits in window t = u - start + (W-1) - w at slot w
        slots = torch.arange(w, device=rows.device)
        t = (ui - self.hist.start + (w - 1)).unsqueeze(1) - slots  # [K, W]
        inside = (t >= 0) & (t < steps)
        window = (ei * self.episodes + bi).unsqueeze(1) * steps + t
        size = ei.new_tensor(self.actions.shape[0] * self.episodes * steps)
        to_sum = torch.where(inside, window, size)
        to_agent = torch.where(inside, window * n + ni.unsqueeze(1), size * n)
        return rows, counts, to_agent, to_sum


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
    """The critic input of `agent_blocks_dense`: lazily as `AgentBlocks` when `hist` is an
    `obs_history` result (or a time slice of one) of this window, else dense. Both hold the
    same values.

    Shapes: hist [E, B, T', N, W*O], actions [E, B, T', N] -> [E, B*T', N*block].
    """
    if isinstance(hist, ObsWindows) and hist.window == window:
        return AgentBlocks(hist, actions, n_actions)
    return agent_blocks_dense(hist, actions, n_actions)


def joint_obs(obs: torch.Tensor) -> torch.Tensor:
    """[E, B, T', N, O] -> [E, B, T', N*O]: the joint observation (QMIX without state)."""
    return obs.flatten(-2)


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-member mean over the real entries: x, mask [E, ...] -> [E]."""
    dims = tuple(range(1, x.dim()))
    return (x * mask).sum(dims) / mask.sum(dims).clamp_min(1.0)


def greedy_actions(q: torch.Tensor, avail: torch.Tensor) -> torch.Tensor:
    """The best available action under q (ties: the lowest index), without gradient.

    Shapes: q, avail [..., A] -> [...] (long).
    """
    return q.detach().masked_fill(~avail, -1e10).argmax(-1)


class AllSteps:
    """Every step of a padded batch, laid out as it is ([E, B, T, ...]): what a central
    critic computes on when its inputs span several steps (`obs_history` windows longer than
    one); `RealSteps` is the packed alternative, with the same interface.

    `take(v, shift)` is steps shift .. shift+T-1 of a time-indexed v [E, B, T', ...];
    `hist(shift)` the same steps of the observation windows; `put` is the identity, and `mask`
    the batch's [E, B, T]."""

    def __init__(self, tb: TensorBatch, window: int):
        self.steps, self.mask = tb.shape[2], tb.mask
        self._hist = obs_history(tb.obs, window)

    def take(self, v: torch.Tensor, shift: int = 0) -> torch.Tensor:
        return v[:, :, shift : shift + self.steps]

    def hist(self, shift: int = 0) -> torch.Tensor:
        return self.take(self._hist, shift)

    def put(self, v: torch.Tensor) -> torch.Tensor:
        return v


class RealSteps:
    """The real steps of a padded batch packed together, for inputs of one step each (an
    observation window of 1): the same interface as `AllSteps`, with every [E, B, T, ...]
    laid out as [E, 1, K, ...], K the largest member's count of real steps.

    A member's real steps come first, in (episode, step) order; its other K - count entries
    are padded steps of its own (`mask` 0 there), so `put` writes K distinct steps back. A
    critic over such inputs computes nothing for padding (a quarter to two fifths of the rows
    of a 3m or 8m batch)."""

    def __init__(self, tb: TensorBatch):
        e, b, t, _ = tb.shape
        real = tb.mask.reshape(e, b * t) > 0
        k = max(int(real.sum(1).max()), 1)
        # a stable sort of "not real" puts each member's real steps first, in order
        self.index = torch.sort((~real).to(torch.uint8), dim=1, stable=True).indices[:, :k]
        self.mask = real.gather(1, self.index).to(tb.mask.dtype).unsqueeze(1)  # [E, 1, K]
        self.episodes, self.steps = b, t
        self._obs = tb.obs

    def take(self, v: torch.Tensor, shift: int = 0) -> torch.Tensor:
        """Steps shift .. of v [E, B, T', ...] at the packed entries, [E, 1, K, ...]."""
        e, k = self.index.shape
        rest = v.shape[3:]
        rows = v.reshape(-1, *rest).index_select(0, self._rows(v.shape[2], shift))
        return rows.view(e, 1, k, *rest)

    def _rows(self, tp: int, shift: int) -> torch.Tensor:
        """The flat [E*B*T'] row of every packed entry's step + shift, [E*K] (row look-ups:
        several times cheaper than a gather along one axis of [E, B*T', ...])."""
        e = self.index.shape[0]
        member = torch.arange(e, device=self.index.device).view(e, 1) * (self.episodes * tp)
        return (member + (self.index // self.steps) * tp + self.index % self.steps + shift).view(-1)

    def hist(self, shift: int = 0) -> torch.Tensor:
        obs = self.take(self._obs, shift)
        _remember_l1(obs, self.take(obs_l1(self._obs), shift))  # the agents' inputs had them
        return obs_history(obs, 1)

    def put(self, v: torch.Tensor) -> torch.Tensor:
        """[E, 1, K, ...] -> [E, B, T, ...], zero at the padded steps."""
        e, k = self.index.shape
        rest = v.shape[3:]
        v = v * self.mask.view(e, 1, k, *(1,) * len(rest))
        out = v.new_zeros(e * self.episodes * self.steps, *rest)
        out.index_copy_(0, self._rows(self.steps, 0), v.reshape(e * k, *rest))
        return out.view(e, self.episodes, self.steps, *rest)
