"""RDN's central critic input kept as its parts, and the layout of the steps it runs on.

The critic's input repeats every observation in W windows and is mostly zeros on large maps
(dead agents, padding): on bane_vs_bane [B*T, 24 agents x (4 x 336 + 30 + 24)] = 3,000 x
33,552 floats, 430 MB. `ObsWindows` and `AgentBlocks` keep its parts instead (the observations,
the actions) and the critic's first layer and LRP's per-agent sums read those
(`learner.critic_layer`); `.dense()` gives the tensor itself, as `learner.rdn_reference`
builds it. `AllSteps` and `RealSteps` lay a padded batch's steps out for the critic.
"""

from __future__ import annotations

import torch

from learner.batch import TensorBatch, nonzero_obs, obs_l1, remember_l1
from learner.critic_layer import block_preactivation, encoder_preactivation
from learner.networks import AgentBlockLinear, EnsembleLinear
from learner.rdn_reference import critic_inputs, obs_windows


def obs_history(obs: torch.Tensor, window: int) -> ObsWindows:
    """Each step's last `window` observations, oldest first, zero before the episode start.

    Returned as `ObsWindows`, which keeps `obs` (`.dense()`: the windows themselves,
    `learner.rdn_reference.obs_windows`); `AgentBlocks` reads the observations from it.

    Args:
        obs: [E, B, T', N, O].
    Returns:
        [E, B, T', N, window * O].
    """
    return ObsWindows(obs, window)


class ObsWindows:
    """The windows of `obs_history` for steps start .. start+steps-1 of obs, [E, B, steps, N,
    window * O], kept as obs. Indexing [:, :, lo:hi] (steps along time) gives another
    ObsWindows of the same obs, sharing its caches; `dense()` builds the windows."""

    def __init__(self, obs: torch.Tensor, window: int, start: int = 0, steps: int | None = None):
        e, b, tp, n, o = obs.shape
        self.obs, self.window, self.start = obs, window, start
        self.steps = tp - start if steps is None else steps
        self.shape = torch.Size((e, b, self.steps, n, window * o))
        self._norms: list[torch.Tensor] = []  # shared by every slice of the same windows
        self._alive: list[tuple] = []  # likewise

    def dense(self) -> torch.Tensor:
        stop = self.start + self.steps
        return obs_windows(self.obs[:, :, :stop], self.window)[:, :, self.start :]

    def __getitem__(self, index: tuple) -> ObsWindows:
        """A time slice [:, :, lo:hi] (the only indexing there is)."""
        everything = slice(None)
        if (
            not isinstance(index, tuple)
            or len(index) != 3
            or index[:2] != (everything, everything)
            or not isinstance(index[2], slice)
            or index[2].step not in (None, 1)
        ):
            raise IndexError("ObsWindows takes [:, :, lo:hi] (steps along time) only")
        lo, hi, _ = index[2].indices(self.steps)
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


class AgentBlocks:
    """A central critic's input x [E, B*T', N*block] with block = [the agent's window of
    observations (W*O), its action one-hot (A), its id one-hot (N)], kept as its parts: the
    windows (an `ObsWindows`), the actions and A. `dense()` is x itself
    (`learner.rdn_reference.critic_inputs`).

    `block_l1`, `alive_rows` and `action_index` are what the critic's first layer
    (`first_layer`) and LRP's per-agent sums (`learner.rdn_fast`,
    `learner.critic_layer.block_dot`) need. Built by `agent_blocks`.

    Series index s (0 .. T'+W-2) is observation step hist.start + s - (W-1): window t holds
    series rows t .. t+W-1.
    """

    def __init__(self, hist: ObsWindows, actions: torch.Tensor, a: int):
        e, b, tp, n, wo = hist.shape
        self.shape = torch.Size((e, b * tp, n * (wo + a + n)))
        self.hist, self.actions, self.n_actions = hist, actions, a
        self.episodes, self.steps, self.n_agents = b, tp, n
        self.obs_dim, self.window = hist.obs.shape[-1], hist.window
        self.block = wo + a + self.n_agents
        self._rows: tuple | None = None

    def dense(self) -> torch.Tensor:
        return critic_inputs(self.hist.dense(), self.actions, self.n_actions)

    def first_layer(self, layer: EnsembleLinear | AgentBlockLinear) -> torch.Tensor:
        """The critic's first layer on x (its pre-activation), without building x."""
        if isinstance(layer, AgentBlockLinear):
            return encoder_preactivation(layer, self)
        return block_preactivation(layer, self)

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


def agent_blocks(
    hist: torch.Tensor, actions: torch.Tensor, n_actions: int, window: int
) -> AgentBlocks | torch.Tensor:
    """The critic input of `learner.rdn_reference.critic_inputs`: as `AgentBlocks` when `hist`
    is an `obs_history` result (or a time slice of one) of this window, else dense. Both hold
    the same values.

    Shapes: hist [E, B, T', N, W*O], actions [E, B, T', N] -> [E, B*T', N*block].
    """
    if isinstance(hist, ObsWindows) and hist.window == window:
        return AgentBlocks(hist, actions, n_actions)
    return critic_inputs(hist, actions, n_actions)


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
        remember_l1(obs, self.take(obs_l1(self._obs), shift))  # the agents' inputs had them
        return obs_history(obs, 1)

    def put(self, v: torch.Tensor) -> torch.Tensor:
        """[E, 1, K, ...] -> [E, B, T, ...], zero at the padded steps."""
        e, k = self.index.shape
        rest = v.shape[3:]
        v = v * self.mask.view(e, 1, k, *(1,) * len(rest))
        out = v.new_zeros(e * self.episodes * self.steps, *rest)
        out.index_copy_(0, self._rows(self.steps, 0), v.reshape(e * k, *rest))
        return out.view(e, self.episodes, self.steps, *rest)
