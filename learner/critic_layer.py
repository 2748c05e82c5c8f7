"""The central critic's first layer on an `AgentBlocks` input (`learner.critic_inputs`),
without building the dense input, and the per-agent sums LRP needs from it (`block_dot`).

Each observation is multiplied once by the weights of its W window slots, all-zero
observations (dead agents, padding) are skipped, and the one-hots are row look-ups: the same
values as the dense product x @ W, which multiplies each observation W times, mostly zeros.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch.nn import functional as F

if TYPE_CHECKING:
    from learner.critic_inputs import AgentBlocks
    from learner.networks import AgentBlockLinear, EnsembleLinear


def block_preactivation(
    layer: EnsembleLinear, x: AgentBlocks, proj: torch.Tensor | None = None
) -> torch.Tensor:
    """layer(x) for an AgentBlocks x, [E, M, H], differentiable in the layer's weight and bias
    (with `proj` given, for use without gradients: nothing flows back through `proj`).

    Agent i's block contributes Σ_w obs_{t-W+1+w, i} W_i,w + W_i,action[a_i] + W_i,id[i],
    where W_i,w are the rows of agent i's window slot w. Every non-zero observation is
    multiplied once by the weights of all W slots (`project_rows`; pass `proj` if the caller
    has it) and added into the W windows it sits in; all-zero observations (dead agents,
    padding) are skipped, and the one-hots are row look-ups. The dense product x @ W
    multiplies each observation W times, mostly zeros. The backward (`_BlockLayer`) writes
    the weight's gradient block by block into one tensor."""
    if proj is None:
        return _BlockLayer.apply(layer.weight, layer.bias, x)
    return _preactivation(layer.weight, layer.bias, x, proj)


def encoder_preactivation(layer: AgentBlockLinear, x: AgentBlocks) -> torch.Tensor:
    """layer(x) for an AgentBlocks x, [E, M, N*H], differentiable in the layer's weights,
    without the dense x: every non-zero observation (`AgentBlocks.alive_rows`) is multiplied
    once by the shared weights of all W window slots and added into the windows it sits in;
    all-zero observations (dead agents, padding: half the rows of a random-policy batch on
    8m) are skipped, and the one-hots are row look-ups."""
    e, m, _ = x.shape
    n, w, o, a, h = x.n_agents, x.window, x.obs_dim, x.n_actions, layer.hidden
    weight = layer.block_weight
    # action row + id row + bias for every (member, agent, action), then one zero row: the
    # one-hot part of every entry is one look-up, and the extra entry (where windows outside
    # these steps are added) is zero
    onehots = (
        weight[:, w * o : w * o + a].view(e, 1, a, h)
        + weight[:, w * o + a :].view(e, n, 1, h)
        + layer.block_bias.view(e, 1, 1, h)
    )
    table = torch.cat([onehots.reshape(e * n * a, h), weight.new_zeros(1, h)])
    agents = torch.arange(e * n, device=weight.device).view(e, 1, 1, n) * a
    rows = F.pad((x.actions + agents).reshape(-1), (0, 1), value=e * n * a)
    z = table.index_select(0, rows)  # [E*M*N + 1, H]
    obs, counts, to_agent, _ = x.alive_rows()  # sorted by member first
    w_obs = weight[:, : w * o].view(e, w, o, h).transpose(1, 2).reshape(e, o, w * h)
    lo = 0
    for k in range(e):
        count = sum(counts[k * n : (k + 1) * n])
        if count:
            proj = obs[lo : lo + count] @ w_obs[k]  # [K_k, W*H], slot-major
            z.index_add_(0, to_agent[lo : lo + count].reshape(-1), proj.view(-1, h))
            lo += count
    return z[:-1].view(e, m, n * h)


# block_dot builds each agent's first-layer contribution c when the live (row, window slot)
# pairs are at least this many times the (row, agent) entries of c
_BUILD_C = 1.5


def block_dot(
    layer: EnsembleLinear, x: AgentBlocks, s: torch.Tensor, proj: torch.Tensor | None = None
) -> torch.Tensor:
    """Σ_h c_ih s_h for every row and agent, [E, M, N], where c_i [E, M, H] is agent i's
    block's part of `block_preactivation(layer, x)` (without the bias) and s [E, M, H] (e.g.
    LRP's relevance ratios of the first layer). Where most agents are alive, c (without its
    one-hot parts) is summed from the projected observations (`project_rows`) and dotted with
    s; where many are dead, c is never built: each projected observation is dotted with s at
    the W windows it sits in and the sums are added into its agent's entries. The one-hot
    parts are s times the action and id rows."""
    e, m, _ = x.shape
    n, a, h = x.n_agents, x.n_actions, layer.out_features
    proj = project_rows(layer, x) if proj is None else proj
    _, _, to_agent, to_sum = x.alive_rows()  # [K, W] each; a window outside: the extra row
    if to_agent.numel() >= _BUILD_C * e * m * n:
        # most (row, slot) pairs are alive: summing them into c [E, M, N, H] and dotting that
        # with s reads fewer bytes than gathering s for every pair (3m: 2.5x cheaper at E = 3)
        c = s.new_zeros(e * m * n + 1, h).index_add_(0, to_agent.view(-1), proj.view(-1, h))
        hist = torch.linalg.vecdot(c[:-1].view(e, m, n, h), s.unsqueeze(2))
    else:  # many dead agents (bane_vs_bane): only the live pairs, s gathered for each
        s_rows = torch.cat([s.reshape(-1, h), s.new_zeros(1, h)])
        g = s_rows.index_select(0, to_sum.view(-1))  # s at the window each (row, slot) fills
        dots = (proj.view(-1, h) * g).sum(-1)  # [K*W]: row k's slot w dotted with its window
        buf = s.new_zeros(e * m * n + 1).index_add_(0, to_agent.view(-1), dots)
        hist = buf[:-1].view(e, m, n)
    w_act, w_id = _onehot_weights(layer.weight, x)
    act = torch.bmm(s, w_act.view(e, n * a, h).transpose(1, 2)).view(e, m, n, a)
    own_action = act.gather(-1, x.actions.reshape(e, m, n, 1)).squeeze(-1)
    return hist + own_action + torch.bmm(s, w_id.transpose(1, 2))


def project_rows(layer: EnsembleLinear, x: AgentBlocks) -> torch.Tensor:
    """Every non-zero observation (`AgentBlocks.alive_rows`) times its agent's weights of all
    W window slots ([K, O] x [O, W*H] per member and agent), [K, W*H], slot-major (no
    gradient)."""
    with torch.no_grad():
        return _project(layer.weight, x)


def _project(weight: torch.Tensor, x: AgentBlocks) -> torch.Tensor:
    e, n, w, o, h = x.shape[0], x.n_agents, x.window, x.obs_dim, weight.shape[-1]
    wb = weight.view(e, n, x.block, h)
    w_obs = wb[:, :, : w * o].reshape(e, n, w, o, h).permute(0, 1, 3, 2, 4)
    w_obs = w_obs.reshape(e * n, o, w * h)  # agent i's [O, W*H] for each member (one copy)
    rows, counts, _, _ = x.alive_rows()
    out = rows.new_empty(rows.shape[0], w * h)
    start = 0
    for g, k in enumerate(counts):  # each group's product written in place
        if k:
            torch.mm(rows[start : start + k], w_obs[g], out=out[start : start + k])
            start += k
    return out


def _preactivation(
    weight: torch.Tensor, bias: torch.Tensor, x: AgentBlocks, proj: torch.Tensor
) -> torch.Tensor:
    """The first layer's pre-activation [E, M, H] from the projected rows `proj`."""
    e, m, _ = x.shape
    h = weight.shape[-1]
    _, _, _, to_sum = x.alive_rows()  # [K, W]; a window outside these steps: the extra row
    hist = proj.new_zeros(e * m + 1, h).index_add_(0, to_sum.view(-1), proj.view(-1, h))
    w_act, w_id = _onehot_weights(weight, x)
    actions = F.embedding_bag(x.action_index().view(e * m, -1), w_act, mode="sum")
    const = (w_id.sum(1) + bias.squeeze(1)).unsqueeze(1)  # the ids and the bias, [E, 1, H]
    return hist[:-1].view(e, m, h) + actions.view(e, m, h) + const


def _onehot_weights(weight: torch.Tensor, x: AgentBlocks) -> tuple[torch.Tensor, torch.Tensor]:
    """The action one-hot rows as [E*N*A, H] (`AgentBlocks.action_index` order) and each
    agent's own id row [E, N, H]."""
    e, n, a, wo = x.shape[0], x.n_agents, x.n_actions, x.window * x.obs_dim
    wb = weight.view(e, n, x.block, weight.shape[-1])
    w_act = wb[:, :, wo : wo + a].reshape(e * n * a, -1)
    w_id = torch.diagonal(wb[:, :, wo + a :], dim1=1, dim2=2).transpose(1, 2)
    return w_act, w_id


class _BlockLayer(torch.autograd.Function):
    """`block_preactivation` with its backward written out: the gradient of the weight
    [E, N*block, H] is filled block by block in one tensor (each agent's observation rows by
    one product per agent, its action rows by index_add, its id row by a sum) instead of
    autograd's one full-size tensor per slice of the weight.

    Kept for its measured gain, and because its rounding is the committed results': used only
    by a critic without an agent encoder (the matrix games and `recipe=seed`), a whole RDN
    update with `recipe=seed` took 8% longer with plain autograd through the same forward on
    skirmish/8m (171 against 158 ms) and bane_vs_bane (1,757 against 1,624 ms), and the same
    on 3m (80 against 86 ms; 32 episodes, E = 1, one process stepping two learners from the
    same weights alternately, 40 updates each, load average 7-8 on 2 shared cores). Plain
    autograd's weight gradient differs in the last bits (3e-5 at most on 3m), which would move
    the matrix games' committed runs."""

    @staticmethod
    def forward(ctx, weight: torch.Tensor, bias: torch.Tensor, x: AgentBlocks) -> torch.Tensor:
        ctx.x = x
        return _preactivation(weight, bias, x, _project(weight, x))

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x = ctx.x
        e, m, h = grad.shape
        n, w, o, a, block = x.n_agents, x.window, x.obs_dim, x.n_actions, x.block
        rows, counts, _, to_sum = x.alive_rows()
        flat = torch.cat([grad.reshape(e * m, h), grad.new_zeros(1, h)])
        g = flat.index_select(0, to_sum.view(-1)).view(-1, w * h)  # each (row, slot)'s window
        g_obs = grad.new_empty(e * n, o, w * h)
        start = 0
        for group, k in enumerate(counts):
            if k:
                part = slice(start, start + k)
                torch.mm(rows[part].t(), g[part], out=g_obs[group])
                start += k
            else:
                g_obs[group].zero_()
        grad_w = grad.new_zeros(e, n, block, h)
        grad_w[:, :, : w * o] = g_obs.view(e, n, o, w, h).transpose(2, 3).reshape(e, n, w * o, h)
        # action rows: (e*N + i)*A + a (action_index) -> row (e*N + i)*block + W*O + a
        index = x.action_index()  # [E, M, N]
        index = index // a * block + w * o + index % a
        src, dest = grad.reshape(e * m, h), grad_w.view(-1, h)
        for i in range(n):
            dest.index_add_(0, index[:, :, i].reshape(-1), src)
        total = grad.sum(1)  # [E, H]: every row holds each agent's id one-hot
        agents = torch.arange(n, device=grad.device)
        grad_w[:, agents, w * o + a + agents] = total.unsqueeze(1)
        return grad_w.view(e, n * block, h), total.unsqueeze(1), None
