"""Layer-wise relevance propagation (LRP-ε) over the central critic MLP, as pure functions.

RDN splits the critic's value Q_tot(x) into per-agent targets: each agent's target is the sum
of the relevance of its own input block (its observations, action one-hot and id one-hot).

The ε-rule for a layer z_k = Σ_j a_j w_jk + b_k with output relevance R_k gives each input
    R_j = a_j Σ_k w_jk R_k / (z_k + ε·sign(z_k)).

Bias handling (the `rule` argument), and why:
* "eps_residual" (default): the bias stays in the denominator, so a unit's relevance is split
  in proportion to what each input actually contributed to the pre-activation the network
  computed. The share a layer's bias and ε absorb is not thrown away: the total residual
  Q_tot - Σ_j R_j is spread over the inputs in proportion to |x_j|. The result conserves
  exactly (Σ_j R_j = Q_tot up to float rounding), so the agents' targets add up to the critic's
  value the way VDN's utilities add up to Q_tot, and an input that is zero still gets exactly
  zero relevance (an agent whose observations are all zero keeps only the relevance of its
  id and action bits).
* "eps": plain LRP-ε with the bias in the denominator; what biases absorb is lost, so
  Σ_j R_j ≠ Q_tot in general.
* "eps_nobias": the bias is left out of the denominator, so every layer passes all of its
  relevance down (conservative up to ε) but the split no longer matches the forward pass.
* "grad_x_input": R_j = x_j ∂Q_tot/∂x_j, the gradient-times-input baseline.
Which rule trains RDN best is measured, not assumed: see `credit repro matrix` and
results/matrix/.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch.nn import functional as F

from learner.batch import AgentBlocks
from learner.lazy import LazyTensor
from learner.networks import (
    MLP,
    AgentBlockLinear,
    block_dot,
    block_preactivation,
    project_rows,
)

LrpRule = Literal["eps_residual", "eps", "eps_nobias", "grad_x_input"]
LRP_RULES: tuple[str, ...] = ("eps_residual", "eps", "eps_nobias", "grad_x_input")


def _share(weight: torch.Tensor) -> torch.Tensor:
    """Each entry's fraction of its row's total (last axis), zero for an all-zero row."""
    total = weight.sum(-1, keepdim=True)
    return torch.where(total > 0, weight / total.clamp_min(1e-12), torch.zeros_like(weight))


def _stabilise(z: torch.Tensor, eps: float) -> torch.Tensor:
    """z + ε·sign(z), with sign(0) = +1 for both zeros (z + 0.0 turns -0.0 into +0.0).

    copysign, not `torch.where(z >= 0, ε, -ε)`: on this CPU build a boolean-mask select
    runs about 15x slower than the three plain passes (6.2 ms against 0.4 ms on an 8m
    batch's [3, 960, 512] first layer)."""
    return torch.copysign(z.new_tensor(eps), z + 0.0).add_(z)


def lrp_epsilon(
    mlp: MLP, x: torch.Tensor, eps: float = 0.01, rule: LrpRule = "eps_residual"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Relevance of every input feature for the (single) output of `mlp`.

    For an `AgentBlocks` input (RDN's critic input) the relevance comes back as a
    `BlockRelevance`: the same values (computed only if used as a tensor), with each agent's
    sum already known, so `agent_relevance` costs nothing and the input is never built densely.

    Args:
        mlp: a ReLU MLP with one output unit.
        x: inputs, [E, M, D].
        eps: ε of the ε-rule (> 0).
        rule: bias handling; see the module docstring.
    Returns:
        (relevance [E, M, D], output [E, M]).
    """
    encoder = isinstance(mlp.layers[0], AgentBlockLinear)
    if isinstance(x, AgentBlocks) and not encoder:
        return _lrp_blocks(mlp, x, eps, rule)
    if rule == "grad_x_input":
        return _grad_x_input(mlp, x.dense() if isinstance(x, AgentBlocks) else x)
    if encoder:
        return _lrp_encoder(mlp, x, eps, rule)
    with torch.no_grad():
        acts = mlp.activations(x)
        out = acts[-1]
        relevance = out
        for layer, a in zip(reversed(mlp.layers), reversed(acts[:-1]), strict=True):
            z = layer.matmul(a)
            if rule != "eps_nobias":
                z = z + layer.bias
            s = relevance / _stabilise(z, eps)
            relevance = a * layer.matmul_t(s)
        out = out.squeeze(-1)
        if rule == "eps_residual":
            residual = out - relevance.sum(-1)
            weight = x.abs()
            share = _share(weight)
            relevance = relevance + residual.unsqueeze(-1) * share
    return relevance, out


class AgentRelevance(LazyTensor):
    """LRP relevance of a critic input that already knows each agent's sum, `per_agent`
    [E, M, N], and the forward pass LRP made on x, which `critic_all_actions` reuses: the
    critic's first layer, `first_preactivation`, and, for a critic with an encoder, its second,
    `second_preactivation` (None otherwise). The dense values are computed only if used as a
    tensor."""

    per_agent: torch.Tensor
    first_preactivation: torch.Tensor
    second_preactivation: torch.Tensor | None = None


class BlockRelevance(AgentRelevance):
    """LRP relevance [E, M, N*block] of an `AgentBlocks` input, kept as each agent's sum
    (`per_agent` [E, M, N]) and what the dense values need: relevance = x * (s @ W1ᵀ), plus
    for eps_residual the residual spread over the inputs in proportion to |x_j|.
    `first_preactivation` [E, M, H] is the critic's first layer on x, which LRP computes
    anyway (`critic_all_actions` reuses it)."""

    def __new__(cls, x: AgentBlocks, *args, **kwargs):
        return super().__new__(cls, tuple(x.shape), x)

    def __init__(
        self,
        x: AgentBlocks,
        per_agent: torch.Tensor,
        s1: torch.Tensor,
        w1: torch.Tensor,
        residual: torch.Tensor | None,
        first_preactivation: torch.Tensor,
    ):
        super().__init__(tuple(x.shape), x)
        self.x, self.per_agent, self.s1, self.w1, self.residual = x, per_agent, s1, w1, residual
        self.first_preactivation = first_preactivation
        self.w1_version = w1._version  # shared with the critic's weight: no copy kept

    def materialise(self) -> torch.Tensor:
        if self.w1._version != self.w1_version:
            raise RuntimeError(
                "the critic's first layer changed after this relevance was computed "
                "(an optimiser step); compute lrp_epsilon again for its per-feature values"
            )
        x = self.x.dense()
        relevance = x * torch.bmm(self.s1, self.w1.transpose(1, 2))
        if self.residual is not None:
            weight = x.abs()
            share = _share(weight)
            relevance = relevance + self.residual.unsqueeze(-1) * share
        return relevance


def _lrp_blocks(
    mlp: MLP, x: AgentBlocks, eps: float, rule: LrpRule
) -> tuple[BlockRelevance, torch.Tensor]:
    """`lrp_epsilon` on an AgentBlocks input. The first layer is linear, so agent i's summed
    first-layer relevance Σ_{j in block i} x_j Σ_k w_jk s_k is Σ_k s_k c_ik, with c_i its
    block's contribution to the pre-activation (`block_dot`, which never builds c); the
    layers above run as in the dense rule. grad_x_input likewise: Σ_k (∂out/∂z1_k) c_ik."""
    first = mlp.layers[0]
    with torch.no_grad():
        proj = project_rows(first, x)  # each observation times its window slots' weights
        z1 = block_preactivation(first, x, proj)
    if rule == "grad_x_input":
        with torch.enable_grad():
            z = z1.detach().requires_grad_(True)
            a = z
            for layer in mlp.layers[1:]:
                a = layer(torch.relu(a))
            (s1,) = torch.autograd.grad(a.sum(), z)
        out = a.detach().squeeze(-1)
        with torch.no_grad():
            per_agent = block_dot(first, x, s1, proj)
        return BlockRelevance(x, per_agent, s1, first.weight.detach(), None, z1), out
    with torch.no_grad():
        s1, out, _ = _first_layer_ratios(mlp, z1, eps, rule)
        per_agent = block_dot(first, x, s1, proj)  # [E, M, N]
        residual = None
        if rule == "eps_residual":
            residual = out - per_agent.sum(-1)
            weight = x.block_l1()
            share = _share(weight)
            per_agent = per_agent + residual.unsqueeze(-1) * share
    return BlockRelevance(x, per_agent, s1, first.weight.detach(), residual, z1), out


def _first_layer_ratios(
    mlp: MLP, z1: torch.Tensor, eps: float, rule: LrpRule
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ε-rule from the output down to the first layer, given that layer's pre-activation
    z1 [E, M, H]: (s1 = R1 / (z1 + ε·sign(z1)) [E, M, H], the critic's output [E, M], the
    second layer's pre-activation [E, M, H2]); the first layer's input relevance is then
    x_j Σ_k w_jk s1_k."""
    first = mlp.layers[0]
    zs, acts = [z1], []
    for layer in mlp.layers[1:]:
        acts.append(torch.relu(zs[-1]))
        zs.append(layer(acts[-1]))
    out = zs[-1]
    relevance = out
    for k in range(len(mlp.layers) - 1, 0, -1):
        layer = mlp.layers[k]
        z = zs[k] if rule != "eps_nobias" else layer.matmul(acts[k - 1])
        s = relevance / _stabilise(z, eps)
        relevance = acts[k - 1] * layer.matmul_t(s)
    s1 = relevance / _stabilise(z1 if rule != "eps_nobias" else z1 - first.bias, eps)
    return s1, out.squeeze(-1), zs[1]


class EncoderRelevance(AgentRelevance):
    """LRP relevance [E, M, N*block] of the dense input x of a critic whose first layer is an
    `AgentBlockLinear` encoder, kept as each agent's sum (`per_agent` [E, M, N]): unit k of
    agent i sees only agent i's block, so that block's first-layer relevance is
    Σ_k s1_ik (z1_ik - b_k), with no product by the weights. The dense values
    (x * (s1 @ W1ᵀ), plus the eps_residual spread) are computed only if used as a tensor.
    `first_preactivation` [E, M, N*H] is the encoder on x and `second_preactivation` [E, M, H2]
    the layer above it (`critic_all_actions` reuses both)."""

    def __new__(cls, x: torch.Tensor, *args, **kwargs):
        return super().__new__(cls, tuple(x.shape), x)

    def __init__(
        self,
        x: torch.Tensor,
        layer: AgentBlockLinear,
        per_agent: torch.Tensor,
        s1: torch.Tensor,
        residual: torch.Tensor | None,
        first_preactivation: torch.Tensor,
        second_preactivation: torch.Tensor,
    ):
        super().__init__(tuple(x.shape), x)
        self.x, self.layer, self.per_agent, self.s1 = x, layer, per_agent, s1
        self.residual, self.first_preactivation = residual, first_preactivation
        self.second_preactivation = second_preactivation
        self.weight_version = layer.block_weight._version

    def materialise(self) -> torch.Tensor:
        if self.layer.block_weight._version != self.weight_version:
            raise RuntimeError(
                "the critic's encoder changed after this relevance was computed "
                "(an optimiser step); compute lrp_epsilon again for its per-feature values"
            )
        x = self.x.dense() if isinstance(self.x, AgentBlocks) else self.x
        relevance = x * self.layer.matmul_t(self.s1)
        if self.residual is not None:
            relevance = relevance + self.residual.unsqueeze(-1) * _share(x.abs())
        return relevance


def _lrp_encoder(
    mlp: MLP, x: torch.Tensor, eps: float, rule: LrpRule
) -> tuple[EncoderRelevance, torch.Tensor]:
    """`lrp_epsilon` for a critic whose first layer is an `AgentBlockLinear` (x dense or
    `AgentBlocks`, which stays lazy)."""
    first = mlp.layers[0]
    e, m, _ = x.shape
    n, h = first.n_agents, first.hidden
    with torch.no_grad():
        z1 = mlp.first(x)
        s1, out, z2 = _first_layer_ratios(mlp, z1, eps, rule)
        contribution = (z1 - first.bias).view(e, m, n, h)  # each agent's block's, unit by unit
        per_agent = (s1.view(e, m, n, h) * contribution).sum(-1)
        residual = None
        if rule == "eps_residual":
            residual = out - per_agent.sum(-1)
            if isinstance(x, AgentBlocks):
                l1 = x.block_l1()
            else:
                l1 = x.abs().view(e, m, n, first.block).sum(-1)
            per_agent = per_agent + residual.unsqueeze(-1) * _share(l1)
    return EncoderRelevance(x, first, per_agent, s1, residual, z1, z2), out


def _grad_x_input(mlp: MLP, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    with torch.enable_grad():
        xg = x.detach().requires_grad_(True)
        out = mlp(xg).squeeze(-1)
        (grad,) = torch.autograd.grad(out.sum(), xg)
    return (grad * xg).detach(), out.detach()


def agent_relevance(relevance: torch.Tensor, n_agents: int) -> torch.Tensor:
    """Sum the relevance of each agent's contiguous input block.

    Args:
        relevance: [E, M, N * block] with the agents' blocks laid end to end.
        n_agents: N.
    Returns:
        [E, M, N].
    """
    e, m, d = relevance.shape
    if d % n_agents:
        raise ValueError(f"input width {d} is not a multiple of n_agents={n_agents}")
    if isinstance(relevance, AgentRelevance) and relevance.per_agent.shape[-1] == n_agents:
        return relevance.per_agent
    return relevance.view(e, m, n_agents, d // n_agents).sum(-1)


def _counterfactual_forward(
    mlp: MLP, x: torch.Tensor, actions: torch.Tensor, n: int, action_offset: int, a: int
) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor], list[torch.Tensor]]:
    """The critic on every single-agent action change of x (see
    `agent_relevance_all_actions`): the first layer's per-agent contributions [E, M, N, H] and
    weight-row shifts [E, M, N, A, H], then every layer's activations and pre-activations with
    the (agent, action) variants as rows [E, M*N*A, .]."""
    e, m, d = x.shape
    block = d // n
    first = mlp.layers[0]
    w1 = first.weight.view(e, n, block, -1)  # [E, N, block, H]
    contrib = torch.einsum("emnb,enbh->emnh", x.view(e, m, n, block), w1)  # [E, M, N, H]
    w_act = w1[:, :, action_offset : action_offset + a]  # [E, N, A, H]
    h = w_act.shape[-1]
    taken = torch.gather(
        w_act.unsqueeze(1).expand(e, m, n, a, h),
        3,
        actions.view(e, m, n, 1, 1).expand(e, m, n, 1, h),
    )  # [E, M, N, 1, H]
    delta = w_act.unsqueeze(1) - taken  # [E, M, N, A, H]
    z1 = contrib.sum(2)[:, :, None, None, :] + first.bias.view(e, 1, 1, 1, -1) + delta
    acts, zs = [torch.relu(z1).reshape(e, m * n * a, h)], [z1.reshape(e, m * n * a, h)]
    for layer in mlp.layers[1:]:
        z = torch.bmm(acts[-1], layer.weight).add_(layer.bias)
        zs.append(z)
        acts.append(torch.relu(z))
    return contrib, delta, acts, zs


_CACHED_ROWS = 4096  # rows of first-layer pre-activations per chunk in critic_all_actions


def critic_all_actions(
    mlp: MLP,
    x: torch.Tensor,
    actions: torch.Tensor,
    n_agents: int,
    action_offset: int,
    n_actions: int,
    keep: torch.Tensor | None = None,
    lrp: AgentRelevance | None = None,
    value: torch.Tensor | None = None,
) -> torch.Tensor:
    """The critic's value with agent i's action moved to a, the others' fixed, for every
    (i, a): [E, M, N, A] (inputs as in `agent_relevance_all_actions`; x may be the critic's
    `AgentBlocks` input; `lrp`, the relevance `lrp_epsilon` returned for this critic and x,
    whose forward pass is reused, and `value` [E, M], Q_c(x), when the caller has them).

    The first layer is linear, so moving agent i's action from u to a shifts its
    pre-activation by W_i,a - W_i,u: the first layer runs once, on x, and only the layers above
    it run per variant, and only on the variants `keep` [E, M, N, A] selects (e.g. available
    actions at real steps; None: all) other than the taken actions. Every other entry holds
    Q_c(x) itself, which is the exact value of the taken action's entry.
    """
    e, m, n = actions.shape
    a = n_actions
    if isinstance(mlp.layers[0], AgentBlockLinear):
        return _critic_all_actions_encoder(mlp, x, actions, action_offset, a, keep, lrp, value)
    with torch.no_grad():
        z1 = mlp.first(x) if lrp is None else lrp.first_preactivation  # [E, M, H]
        h = z1.shape[-1]
        first = mlp.layers[0]
        w_act = first.weight.view(e, n, -1, h)[:, :, action_offset : action_offset + a]
        w_flat = w_act.reshape(e * n * a, h)  # row (e*N + i)*A + a: agent i's action-a weights
        table = torch.cat([z1.reshape(e * m, h), w_flat])  # rows looked up below
        members = torch.arange(e, device=actions.device).view(e, 1)
        if keep is None:
            keep = torch.ones(e, m, n, a, dtype=torch.bool, device=actions.device)
        keep = keep.clone()  # the taken action's entry is Q_c(x)
        keep.view(-1, a).scatter_(1, actions.reshape(-1, 1), False)
        q_x = (_upper_layers(mlp, z1) if value is None else value).view(e, m, 1, 1)
        out = q_x.expand(e, m, n, a).clone().view(e, m * n * a)
        member, mi, act = keep.view(e, m * n, a).nonzero().unbind(1)  # mi = m*N + i
        counts = torch.bincount(member, minlength=e).tolist()
        width = max(counts, default=0)
        if width == 0:
            return out.view(e, m, n, a)
        # pad every member to the same row count with the first row (never written back)
        slot = torch.arange(width, device=actions.device).expand(e, width)
        starts = torch.tensor([0, *counts[:-1]], device=actions.device).cumsum(0).view(e, 1)
        count = torch.tensor(counts, device=actions.device).view(e, 1)
        src = torch.where(slot < count, starts + slot, 0)
        mi, act = mi[src], act[src]  # [E, width]
        # z = z1[m] - W_i,taken + W_i,a for every picked row, as one weighted sum of three
        # looked-up rows of one table (no intermediate [rows, H] tensors: on bane_vs_bane
        # there are 10^5 rows)
        agent_row = e * m + (members * n + mi % n) * a  # agent i's first action row
        taken = actions.reshape(e, m * n).gather(1, mi)
        triples = torch.stack([mi // n + members * m, agent_row + taken, agent_row + act], -1)
        # in chunks of rows that stay in the cache through every layer (one pass over all
        # 10^5 rows per layer is memory-bound: about twice the time)
        step = max(1, _CACHED_ROWS // e)
        values = z1.new_empty(e, width)
        for lo in range(0, width, step):
            part = triples[:, lo : lo + step].reshape(-1, 3)
            signs = z1.new_tensor([1.0, -1.0, 1.0]).expand(part.shape[0], 3)
            z = F.embedding_bag(part, table, mode="sum", per_sample_weights=signs)
            values[:, lo : lo + step] = _upper_layers(mlp, z.view(e, -1, h), in_place=True)
        for k, c in enumerate(counts):
            out[k, mi[k, :c] * a + act[k, :c]] = values[k, :c]
    return out.view(e, m, n, a)


def _critic_all_actions_encoder(
    mlp: MLP,
    x: torch.Tensor,
    actions: torch.Tensor,
    action_offset: int,
    a: int,
    keep: torch.Tensor | None,
    lrp: AgentRelevance | None,
    value: torch.Tensor | None,
) -> torch.Tensor:
    """`critic_all_actions` for a critic whose first layer is an `AgentBlockLinear` encoder.

    Moving agent i's action from u to a shifts only agent i's H1 encoder units, by the shared
    rows W_a - W_u; in the second layer's pre-activation z2 = b2 + Σ_j relu(z1_j) @ W2_j (W2_j:
    agent j's [H1, H2] slice), only agent i's term changes, so the moved pre-activation is
    z2 + (relu(z1_i + W_a - W_u) - relu(z1_i)) @ W2_i. The encoder and the second layer run
    once, on x (or come from `lrp`), and each kept variant costs one H1 x H2 product (its
    agent's slice, rows grouped by agent) before the layers above, never the dense
    [N*H1, H2] one. The entries `keep` leaves out and the taken actions' hold Q_c(x).
    """
    e, m, n = actions.shape
    enc, second = mlp.layers[0], mlp.layers[1]
    h1, h2 = enc.hidden, second.out_features
    with torch.no_grad():
        if lrp is None or lrp.second_preactivation is None:
            z1 = mlp.first(x)
            z2 = second(torch.relu(z1))
        else:
            z1, z2 = lrp.first_preactivation, lrp.second_preactivation  # [E, M, N*H1], [E, M, H2]
        q_x = _upper_layers(mlp, z2, start=2) if value is None else value  # [E, M]
        out = q_x.view(e, m, 1, 1).expand(e, m, n, a).clone()
        w2 = second.weight.view(e, n, h1, h2)
        # one table of every member's encoder rows (row (k*M + r)*N + i) and action rows
        # (row E*M*N + k*A + a): z1_i - W_u + W_a is a signed sum of three of its rows
        w_act = enc.block_weight[:, action_offset : action_offset + a].reshape(e * a, h1)
        table = torch.cat([z1.reshape(e * m * n, h1), w_act])
        todo = torch.ones_like(out, dtype=torch.bool) if keep is None else keep.clone()
        todo.view(-1, a).scatter_(1, actions.reshape(-1, 1), False)  # the taken: Q_c(x)
        for k in range(e):
            agent, row, act = todo[k].permute(1, 0, 2).nonzero().unbind(1)  # agent-major
            if agent.numel() == 0:
                continue
            unit = (k * m + row) * n + agent  # the (row, agent) encoder row in the table
            taken = actions[k].reshape(m * n).index_select(0, unit - k * m * n)
            actions_row = e * m * n + k * a
            triples = torch.stack([unit, actions_row + taken, actions_row + act], 1)
            signs = table.new_tensor([1.0, -1.0, 1.0]).expand(triples.shape[0], 3)
            moved = F.embedding_bag(triples, table, mode="sum", per_sample_weights=signs)
            moved.relu_().sub_(table.index_select(0, unit).relu_())  # the change of relu(z1_i)
            z = z2[k].index_select(0, row)  # [R, H2], added to in place
            lo = 0
            for i, count in enumerate(torch.bincount(agent, minlength=n).tolist()):
                if count:
                    z[lo : lo + count].addmm_(moved[lo : lo + count], w2[k, i])
                    lo += count
            for layer in mlp.layers[2:]:
                z = torch.addmm(layer.bias[k], z.relu_(), layer.weight[k])
            out[k, row, agent, act] = z.squeeze(-1)
    return out


def _upper_layers(
    mlp: MLP, z1: torch.Tensor, in_place: bool = False, start: int = 1
) -> torch.Tensor:
    """The critic above layer `start - 1`, from that layer's pre-activations [E, R, H] -> [E, R]
    (`in_place`: z1 may be overwritten; every later activation is, as nothing else holds it)."""
    z = z1
    for k, layer in enumerate(mlp.layers[start:]):
        a = torch.relu_(z) if in_place or k > 0 else torch.relu(z)
        z = torch.bmm(a, layer.weight).add_(layer.bias)
    return z.squeeze(-1)


def agent_relevance_all_actions(
    mlp: MLP,
    x: torch.Tensor,
    actions: torch.Tensor,
    n_agents: int,
    action_offset: int,
    n_actions: int,
    eps: float = 0.01,
    rule: LrpRule = "eps_residual",
) -> torch.Tensor:
    """Each agent's LRP share of the critic's value for every action it could have taken,
    the other agents' actions fixed: out[..., i, a] = agent_relevance(lrp_epsilon(mlp, x'))[i]
    where x' is x with agent i's action one-hot moved to a.

    The first layer is linear, so a counterfactual action only shifts its pre-activation by
    the difference of two weight rows; only the layers above it run once per (agent, action),
    and agent i's first-layer relevance is the sum over units of its own pre-activation
    contribution times the unit's relevance ratio. The same numbers as N·A separate calls of
    `lrp_epsilon` at a fraction of their cost.

    Args:
        mlp: the critic, a ReLU MLP with one output.
        x: [E, M, N * block] inputs, each agent's block laid end to end, its action one-hot at
            positions action_offset .. action_offset + n_actions of its block.
        actions: [E, M, N] the actions one-hot encoded in x.
        eps, rule: as in `lrp_epsilon` ("grad_x_input" is not supported here).
    Returns:
        [E, M, N, A].
    """
    if rule == "grad_x_input":
        raise ValueError("agent_relevance_all_actions supports the epsilon rules only")
    e, m, d = x.shape
    n, a = n_agents, n_actions
    block = d // n
    first = mlp.layers[0]
    with torch.no_grad():
        contrib, delta, acts, zs = _counterfactual_forward(mlp, x, actions, n, action_offset, a)
        own = contrib[:, :, :, None, :] + delta  # agent i's own contribution in variant (i, a)
        h = own.shape[-1]
        out = zs[-1]  # the linear output, [E, MNA, 1]
        relevance = out
        for k in range(len(mlp.layers) - 1, 0, -1):
            layer = mlp.layers[k]
            z = zs[k] if rule != "eps_nobias" else zs[k] - layer.bias
            s = relevance / _stabilise(z, eps)
            relevance = acts[k - 1] * torch.bmm(s, layer.weight.transpose(1, 2))
        z_first = zs[0] if rule != "eps_nobias" else zs[0] - first.bias
        s1 = (relevance / _stabilise(z_first, eps)).view(e, m, n, a, h)
        shares = (s1 * own).sum(-1)  # [E, M, N, A]
        if rule == "eps_residual":
            total = (s1 * (zs[0].view(e, m, n, a, h) - first.bias.view(e, 1, 1, 1, -1))).sum(-1)
            residual = out.view(e, m, n, a) - total
            weight = x.abs().view(e, m, n, block).sum(-1)  # a swapped one-hot keeps |x|
            frac = weight / weight.sum(-1, keepdim=True).clamp_min(1e-12)
            shares = shares + residual * frac.unsqueeze(-1)
    return shares


def lrp_difference(
    mlp: MLP, x: torch.Tensor, x_ref: torch.Tensor, eps: float = 0.01
) -> tuple[torch.Tensor, torch.Tensor]:
    """Relevance of each input's deviation from a reference input for the output's deviation:
    the ε-rule applied to differences (a deep-Taylor root point / DeepLIFT's rescale rule),
        R_j = (a_j - ā_j) Σ_k w_jk R_k / (Δz_k + ε·sign(Δz_k)),   R_out = f(x) - f(x_ref),
    with what ε absorbs spread over the inputs in proportion to |x - x_ref| (as
    "eps_residual"), so Σ_j R_j = f(x) - f(x_ref) exactly and an input equal to its
    reference gets no relevance.

    Args:
        mlp: a ReLU MLP with one output unit.
        x, x_ref: [E, M, D].
    Returns:
        (relevance [E, M, D], f(x) - f(x_ref) [E, M]).
    """
    with torch.no_grad():
        acts, refs = mlp.activations(x), mlp.activations(x_ref)
        delta_out = (acts[-1] - refs[-1]).squeeze(-1)
        relevance = delta_out.unsqueeze(-1)
        for k in range(len(mlp.layers) - 1, -1, -1):
            layer = mlp.layers[k]
            da = acts[k] - refs[k]
            dz = layer.matmul(da)
            s = relevance / _stabilise(dz, eps)
            relevance = da * layer.matmul_t(s)
        dx = (x - x_ref).abs()
        total = dx.sum(-1, keepdim=True)
        share = torch.where(total > 0, dx / total.clamp_min(1e-12), torch.zeros_like(dx))
        relevance = relevance + (delta_out - relevance.sum(-1)).unsqueeze(-1) * share
    return relevance, delta_out
