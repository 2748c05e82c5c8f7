"""Networks with a leading ensemble axis E, so several independent seeds train in one call.

Every parameter has shape [E, ...] and every activation [E, M, features]. Members share
nothing: gradients of a sum of per-member losses are per-member gradients, Adam is
elementwise, and `clip_grad_norm_per_member` clips each member by its own norm, so E seeds
trained together follow exactly the updates they would follow apart. E = 1 is a plain run.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from learner.batch import AgentInputLayout, AgentInputs


class EnsembleLinear(nn.Module):
    """E independent affine maps. Shapes: x [E, M, in] -> [E, M, out]."""

    def __init__(self, n_ensemble: int, in_features: int, out_features: int):
        super().__init__()
        self.in_features, self.out_features = in_features, out_features
        bound = 1.0 / math.sqrt(in_features)  # nn.Linear's default initialisation range
        self.weight = nn.Parameter(
            torch.empty(n_ensemble, in_features, out_features).uniform_(-bound, bound)
        )
        self.bias = nn.Parameter(torch.empty(n_ensemble, 1, out_features).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight)

    def matmul_t(self, s: torch.Tensor) -> torch.Tensor:
        """s @ weightᵀ (LRP's way back): [E, M, out] -> [E, M, in]."""
        return torch.bmm(s, self.weight.transpose(1, 2))


class AgentBlockLinear(nn.Module):
    """One affine map shared by N agents' input blocks laid end to end: agent i's block
    [i*block, (i+1)*block) goes to its own H units [i*H, (i+1)*H), with the same weights for
    every agent (a per-agent encoder with parameter sharing, as the agents' networks have).

    As a layer it is the dense layer whose weight is block-diagonal, so `weight` and `bias`
    expose that dense form ([E, N*block, N*H], [E, 1, N*H]) for LRP; `forward` computes it
    per block. Shapes: x [E, M, N*block] -> [E, M, N*H].
    """

    def __init__(self, n_ensemble: int, n_agents: int, block: int, hidden: int):
        super().__init__()
        self.n_agents, self.block, self.hidden = n_agents, block, hidden
        self.in_features, self.out_features = n_agents * block, n_agents * hidden
        bound = 1.0 / math.sqrt(block)
        self.block_weight = nn.Parameter(
            torch.empty(n_ensemble, block, hidden).uniform_(-bound, bound)
        )
        self.block_bias = nn.Parameter(torch.empty(n_ensemble, 1, hidden).uniform_(-bound, bound))

    @property
    def weight(self) -> torch.Tensor:
        eye = torch.eye(
            self.n_agents, dtype=self.block_weight.dtype, device=self.block_weight.device
        )
        full = torch.einsum("ij,epq->eipjq", eye, self.block_weight)
        return full.reshape(-1, self.in_features, self.out_features)

    @property
    def bias(self) -> torch.Tensor:
        return self.block_bias.repeat(1, 1, self.n_agents)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e, m, _ = x.shape
        xb = x.reshape(e, m * self.n_agents, self.block)
        out = torch.baddbmm(self.block_bias, xb, self.block_weight)
        return out.view(e, m, self.out_features)

    def matmul_t(self, s: torch.Tensor) -> torch.Tensor:
        """s @ weightᵀ, block by block (LRP's way back): [E, M, N*H] -> [E, M, N*block]."""
        e, m, _ = s.shape
        sb = s.reshape(e, m * self.n_agents, self.hidden)
        return torch.bmm(sb, self.block_weight.transpose(1, 2)).view(e, m, self.in_features)


class EnsembleGRUCell(nn.Module):
    """E independent GRU cells (PyTorch's gate equations). Shapes: x [E, M, in], h [E, M, H]."""

    def __init__(self, n_ensemble: int, in_features: int, hidden: int):
        super().__init__()
        self.hidden = hidden
        self.ih = EnsembleLinear(n_ensemble, in_features, 3 * hidden)
        self.hh = EnsembleLinear(n_ensemble, hidden, 3 * hidden)
        bound = 1.0 / math.sqrt(hidden)  # nn.GRUCell initialises every tensor in this range
        with torch.no_grad():
            for p in self.parameters():
                p.uniform_(-bound, bound)

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        return self.recur(self.ih(x), h)

    def recur(self, gi: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """One step from a precomputed input projection gi = ih(x) [E, M, 3H] (an unroll
        projects every step's input in one call; only this part is sequential)."""
        gh = self.hh(h)
        i_r, i_z, i_n = gi.chunk(3, dim=-1)
        h_r, h_z, h_n = gh.chunk(3, dim=-1)
        r = torch.sigmoid(i_r + h_r)
        z = torch.sigmoid(i_z + h_z)
        n = torch.tanh(i_n + r * h_n)
        return (1.0 - z) * n + z * h


class AgentNet(nn.Module):
    """The shared agent: GRU(hidden) -> FC(fc) -> FC(fc) -> n_actions (DRQN, the dissertation's), or
    with `recurrent=False` FC(hidden) -> FC(fc) -> FC(fc) -> n_actions (feed-forward; the
    hidden state passes through unchanged, so callers treat both alike).

    Input per agent: own observation, last action one-hot, agent id one-hot. Parameters are
    shared by all agents (the agent axis is folded into M). The head gives Q-values for the
    value family and logits for the policy-gradient family.

    Shapes: inputs [E, M, input_dim], h [E, M, hidden] -> out [E, M, n_actions], h' [E, M, hidden].
    """

    def __init__(
        self,
        n_ensemble: int,
        input_dim: int,
        n_actions: int,
        hidden: int = 64,
        fc: int = 32,
        recurrent: bool = True,
    ):
        super().__init__()
        self.input_dim, self.hidden, self.recurrent = input_dim, hidden, recurrent
        if recurrent:
            self.gru = EnsembleGRUCell(n_ensemble, input_dim, hidden)
        else:
            self.inp = EnsembleLinear(n_ensemble, input_dim, hidden)
        self.fc1 = EnsembleLinear(n_ensemble, hidden, fc)
        self.fc2 = EnsembleLinear(n_ensemble, fc, fc)
        self.out = EnsembleLinear(n_ensemble, fc, n_actions)

    def init_hidden(self, n_ensemble: int, m: int) -> torch.Tensor:
        return self.out.weight.new_zeros(n_ensemble, m, self.hidden)

    def head(self, x: torch.Tensor) -> torch.Tensor:
        """Everything after the GRU (or after the feed-forward input layer)."""
        x = F.relu(self.fc1(x))
        x = F.relu(self.fc2(x))
        return self.out(x)

    def forward(self, inputs: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if not self.recurrent:
            return self.head(F.relu(self.inp(inputs))), h
        h = self.gru(inputs, h)
        return self.head(h), h


class MLP(nn.Module):
    """ReLU MLP with a linear output, e.g. the central critic 64-64-1.

    Shapes: x [E, M, in] -> [E, M, out]. `layers` is exposed for LRP. With `first` given
    (e.g. an `AgentBlockLinear`), that layer comes first and `in_features` is ignored. An
    `AgentBlocks` input (RDN's critic input, kept as its parts) goes through the first layer by
    its own `first_layer`, which multiplies each observation once instead of the dense input.
    """

    def __init__(
        self,
        n_ensemble: int,
        in_features: int,
        hidden: tuple[int, ...],
        out_features: int = 1,
        first: nn.Module | None = None,
    ):
        super().__init__()
        head = [] if first is None else [first]
        sizes = [in_features if first is None else first.out_features, *hidden, out_features]
        self.layers = nn.ModuleList(
            head + [EnsembleLinear(n_ensemble, a, b) for a, b in itertools.pairwise(sizes)]
        )

    def first(self, x: torch.Tensor) -> torch.Tensor:
        """The first layer's pre-activation, [E, M, hidden[0]]. A structured input
        (`learner.critic_inputs.AgentBlocks`) computes it from its parts (`first_layer`)."""
        if isinstance(x, torch.Tensor):
            return self.layers[0](x)
        return x.first_layer(self.layers[0])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.activations(x)[-1]

    def activations(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Inputs of every layer followed by the output: [x, a1, ..., a_L, y]."""
        acts = [x]
        z = self.first(x)
        for layer in self.layers[1:]:
            acts.append(F.relu(z))
            z = layer(acts[-1])
        acts.append(z)
        return acts


class QMixer(nn.Module):
    """QMIX's monotonic mixer: hypernetworks map a conditioning vector to non-negative weights.

    Conditioned on the global state (QMIX) or on the joint observation (the dissertation's QMIX
    without state). Shapes: qs [E, M, N], cond [E, M, cond_dim] -> q_tot [E, M, 1].
    """

    def __init__(
        self, n_ensemble: int, n_agents: int, cond_dim: int, embed: int = 32, hyper_hidden: int = 64
    ):
        super().__init__()
        self.n_agents, self.embed = n_agents, embed
        self.hyper_w1 = MLP(n_ensemble, cond_dim, (hyper_hidden,), n_agents * embed)
        self.hyper_w2 = MLP(n_ensemble, cond_dim, (hyper_hidden,), embed)
        self.hyper_b1 = EnsembleLinear(n_ensemble, cond_dim, embed)
        self.value = MLP(n_ensemble, cond_dim, (embed,), 1)

    def forward(self, qs: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        # Each row mixes its own N values with its own weights: products summed elementwise,
        # not one [1, N] x [N, embed] bmm per row (2-3x cheaper for these tiny matrices).
        e, m, n = qs.shape
        w1 = self.hyper_w1(cond).abs().view(e, m, n, self.embed)
        hidden = F.elu((qs.unsqueeze(-1) * w1).sum(-2) + self.hyper_b1(cond))  # [E, M, embed]
        w2 = self.hyper_w2(cond).abs()  # [E, M, embed]
        return (hidden * w2).sum(-1, keepdim=True) + self.value(cond)


def clip_grad_norm_per_member(params: list[nn.Parameter], max_norm: float) -> torch.Tensor:
    """Clip each ensemble member's gradient to `max_norm` by its own global norm.

    Returns the per-member norms before clipping, shape [E].
    """
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return torch.zeros(0)
    sq = sum(g.pow(2).reshape(g.shape[0], -1).sum(dim=1) for g in grads)
    norms = sq.sqrt()
    scale = (max_norm / (norms + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(scale.view(-1, *([1] * (g.dim() - 1))))
    return norms


def unroll(agent: AgentNet, inputs: torch.Tensor) -> torch.Tensor:
    """Run the agent over whole episodes: recurrent from a zero hidden state, step by step;
    feed-forward in one call over every step. `AgentInputs` (what `agent_inputs` returns)
    are projected by `input_projection` without being built.

    Shapes: inputs [E, B, T', N, D] -> outputs [E, B, T', N, A].
    """
    e, b, tp, n, d = inputs.shape
    if not agent.recurrent:
        if isinstance(inputs, AgentInputs):
            first = input_projection(agent.inp, inputs, time_major=False)
        else:
            first = agent.inp(inputs.reshape(e, b * tp * n, d))
        return agent.head(F.relu(first.reshape(e, b * tp * n, -1))).view(e, b, tp, n, -1)
    # The input projection and the layers after the GRU act on every step at once; only the
    # recurrence itself runs step by step (same arithmetic as calling the agent per step).
    if isinstance(inputs, AgentInputs):
        gi = input_projection(agent.gru.ih, inputs, time_major=True).view(e, tp, b * n, -1)
    else:
        gi = agent.gru.ih(inputs.transpose(1, 2).reshape(e, tp * b * n, d)).view(e, tp, b * n, -1)
    h = agent.init_hidden(e, b * n)
    hs = []
    for g in gi.unbind(1):  # unbind, not gi[:, t]: one gradient stack, not one per step
        h = agent.gru.recur(g, h)
        hs.append(h)
    out = agent.head(torch.stack(hs, dim=1).view(e, tp * b * n, -1))
    return out.view(e, tp, b, n, -1).transpose(1, 2)


def input_projection(layer: EnsembleLinear, x: AgentInputs, time_major: bool) -> torch.Tensor:
    """layer(x) for AgentInputs x, [E, T', B, N, H] (time_major) or [E, B, T', N, H]: the
    non-zero observations times the observation rows (one product per member), plus one
    look-up per input in a table of (agent id row + last action row + bias). Differentiable
    in the layer."""
    e, _, _, n, o = x.obs.shape
    a, h = x.n_actions, layer.out_features
    w_obs, w_act, w_id = layer.weight.split(list(AgentInputLayout(o, a, n).parts), dim=1)
    w_last = torch.cat([w_act, w_act.new_zeros(e, 1, h)], dim=1)  # row A: no last action
    table = w_last.unsqueeze(1) + (w_id + layer.bias).unsqueeze(2)  # [E, N, A+1, H]
    out = F.embedding(x.onehot_index(time_major), table.reshape(-1, h))
    rows, counts, flat = x.rows(time_major)
    parts = [torch.mm(r, w) for r, w, k in zip(rows.split(counts), w_obs, counts, strict=True) if k]
    if not parts:
        return out
    # out of place: an in-place index_add_ into a view of `out` makes autograd clone the whole
    # output in the backward (CopySlices), which cost as much as the rest of this layer's
    # forward and backward together; the values and gradients are the same, bit for bit
    # (under bfloat16 autocast the products are bfloat16; the sum stays in out's float32)
    return out.view(-1, h).index_add(0, flat, torch.cat(parts).to(out.dtype)).view(out.shape)


@dataclass(frozen=True)
class ActingSpec:
    """What a rollout worker needs to build and drive the acting network, as the learner
    describes it (`Learner.acting`); plain values, so it crosses process boundaries.

    Attributes:
        layout: the per-agent input (own obs, last action, agent id); its width is the
            network's input width.
        hidden, fc, recurrent: the `AgentNet` architecture (see `learner.common.AgentConfig`).
        policy_kind: "q" (epsilon-greedy on Q-values) or "softmax" (sample the policy).
    """

    layout: AgentInputLayout
    hidden: int
    fc: int
    recurrent: bool
    policy_kind: str

    def build(self, n_ensemble: int = 1) -> AgentNet:
        """A fresh AgentNet of `n_ensemble` members (draws its initial weights from torch's
        global RNG, so a learner building it keeps its seeded initialisation)."""
        lay = self.layout
        return AgentNet(n_ensemble, lay.width, lay.n_actions, self.hidden, self.fc, self.recurrent)


@dataclass(frozen=True)
class VersionedWeights:
    """The acting policy's parameters as numpy arrays, with a monotonically rising version.

    `arrays` maps AgentNet parameter names to arrays of shape [E, ...].
    """

    version: int
    arrays: dict[str, np.ndarray]

    @classmethod
    def from_module(cls, module: nn.Module, version: int) -> VersionedWeights:
        return cls(
            version, {k: v.detach().cpu().numpy().copy() for k, v in module.state_dict().items()}
        )

    def load_into(self, module: nn.Module) -> None:
        module.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in self.arrays.items()})
