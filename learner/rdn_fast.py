"""RDN's agent targets, fast: the numbers of `learner.rdn_reference` (LRP-epsilon shares of the
critic's value, and the counterfactual targets) without the dense relevance or one critic pass
per counterfactual. `agent_targets` is the one entry point (`learner.rdn.RDNLearner.step`);
tests/learner/test_rdn_reference.py holds it equal to the reference on every shipped
configuration.

Two facts make it cheap, both because the critic's first layer is linear:
* agent i's share is the relevance summed over its own block, sum_{j in block i} x_j
  (s1 @ W1^T)_j = sum_k s1_k c_ik, with c_i the block's part of the first layer's
  pre-activation: no per-feature relevance is ever built (`_blocks_shares`, `_encoder_shares`);
* moving agent i's action from u to a shifts that pre-activation by W_i,a - W_i,u, so the
  counterfactual critic runs the first layer once and only the layers above it per kept
  variant (`_moved_values`, `_moved_values_encoder`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch.nn import functional as F

from learner.critic_inputs import AgentBlocks
from learner.critic_layer import block_dot, block_preactivation, project_rows
from learner.networks import MLP, AgentBlockLinear
from learner.rdn_reference import epsilon_rule, lrp_shares, preactivations


class AgentTargets(NamedTuple):
    """What the agents regress onto: `shares` [E, M, N] (each agent's LRP share of the
    critic's value `q` [E, M]) and, for counterfactual targets, `every` [E, M, N, A] (agent
    i's target for action a; None for the taken-action targets)."""

    shares: torch.Tensor
    q: torch.Tensor
    every: torch.Tensor | None


def agent_targets(
    critic: MLP,
    x: AgentBlocks | torch.Tensor,
    actions: torch.Tensor,
    keep: torch.Tensor | None,
    eps: float,
    action_offset: int,
) -> AgentTargets:
    """The agents' targets from `critic` at its input x [E, M, N*block] (an `AgentBlocks` or
    dense) with the joint actions `actions` [E, M, N] in it: `lrp_shares`, and with `keep`
    [E, M, N, A] given (the entries the agents' loss uses) `counterfactual_targets` on those
    entries (`every` holds the share alone elsewhere, whose weight in the loss is zero).
    `action_offset`: where each block's action one-hot starts (W*O)."""
    with torch.no_grad():
        shares, q, zs = _shares(critic, x, eps, actions.shape[-1])
        if keep is None:
            return AgentTargets(shares, q, None)
        if isinstance(critic.layers[0], AgentBlockLinear):
            moved = _moved_values_encoder(critic, zs, actions, action_offset, keep, q)
        else:
            moved = _moved_values(critic, zs[0], actions, action_offset, keep, q)
        every = moved.sub_(q[..., None, None]).add_(shares.unsqueeze(-1))
    return AgentTargets(shares, q, every)


def _shares(
    critic: MLP, x: AgentBlocks | torch.Tensor, eps: float, n_agents: int
) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """(shares [E, M, N], Q_c(x) [E, M], the critic's pre-activations on x)."""
    first = critic.layers[0]
    if isinstance(first, AgentBlockLinear):
        return _encoder_shares(critic, x, eps)
    if isinstance(x, AgentBlocks):
        return _blocks_shares(critic, x, eps)
    shares, q = lrp_shares(critic, x, n_agents, eps)  # a dense input: the reference's way
    return shares, q, preactivations(critic, first(x))


def _spread_residual(
    per_agent: torch.Tensor, q: torch.Tensor, block_l1: torch.Tensor
) -> torch.Tensor:
    """What biases and epsilon absorbed, q - sum of the shares, added to each agent's share in
    proportion to its block's sum of |x_j| (as `lrp_shares` spreads it over the inputs)."""
    residual = q - per_agent.sum(-1)
    total = block_l1.sum(-1, keepdim=True)
    weight = torch.where(total > 0, block_l1 / total.clamp_min(1e-12), torch.zeros_like(block_l1))
    return per_agent + residual.unsqueeze(-1) * weight


def _blocks_shares(critic: MLP, x: AgentBlocks, eps: float):
    """`_shares` for a dense first layer on an AgentBlocks input: agent i's share is
    sum_k s1_k c_ik (`block_dot`, which never builds c)."""
    first = critic.layers[0]
    proj = project_rows(first, x)  # each observation times its window slots' weights
    zs = preactivations(critic, block_preactivation(first, x, proj))
    s1 = epsilon_rule(critic, zs, eps)
    q = zs[-1].squeeze(-1)
    per_agent = block_dot(first, x, s1, proj)  # [E, M, N]
    return _spread_residual(per_agent, q, x.block_l1()), q, zs


def _encoder_shares(critic: MLP, x: AgentBlocks | torch.Tensor, eps: float):
    """`_shares` for an `AgentBlockLinear` first layer: unit k of agent i sees only agent i's
    block, so that block's part of z1_ik is z1_ik - b_k and its share sum_k s1_ik (z1_ik - b_k)."""
    first = critic.layers[0]
    e, m, _ = x.shape
    n, h = first.n_agents, first.hidden
    zs = preactivations(critic, critic.first(x))
    s1 = epsilon_rule(critic, zs, eps)
    q = zs[-1].squeeze(-1)
    contribution = (zs[0] - first.bias).view(e, m, n, h)
    per_agent = (s1.view(e, m, n, h) * contribution).sum(-1)
    l1 = x.block_l1() if isinstance(x, AgentBlocks) else x.abs().view(e, m, n, -1).sum(-1)
    return _spread_residual(per_agent, q, l1), q, zs


def _todo(keep: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """The kept entries other than the taken actions (whose value is Q_c(x) itself)."""
    todo = keep.clone()
    todo.view(-1, keep.shape[-1]).scatter_(1, actions.reshape(-1, 1), False)
    return todo


def _above(critic: MLP, z: torch.Tensor, k: int, start: int) -> torch.Tensor:
    """Member k of the critic above layer `start - 1`, from that layer's pre-activations
    z [R, H] -> [R] (z is overwritten)."""
    for layer in critic.layers[start:]:
        z = torch.addmm(layer.bias[k], z.relu_(), layer.weight[k])
    return z.squeeze(-1)


def _moved_values(
    critic: MLP, z1: torch.Tensor, actions: torch.Tensor, offset: int, keep, q: torch.Tensor
) -> torch.Tensor:
    """Q_c with agent i's action moved to a, the others' fixed, [E, M, N, A], for a dense first
    layer with pre-activation z1 [E, M, H] on x: z1 - W_i,u + W_i,a runs through the layers
    above. Entries `keep` leaves out, and the taken actions', hold Q_c(x) = q [E, M]."""
    e, m, n = actions.shape
    a = keep.shape[-1]
    h = z1.shape[-1]
    w_act = critic.layers[0].weight.view(e, n, -1, h)[:, :, offset : offset + a]  # [E, N, A, H]
    out = q.view(e, m, 1, 1).expand(e, m, n, a).clone()
    todo = _todo(keep, actions)
    for k in range(e):
        row, agent, act = todo[k].nonzero().unbind(1)
        taken = actions[k, row, agent]
        z = z1[k, row] - w_act[k, agent, taken] + w_act[k, agent, act]
        out[k, row, agent, act] = _above(critic, z, k, 1)
    return out


def _moved_values_encoder(
    critic: MLP, zs: list[torch.Tensor], actions: torch.Tensor, offset: int, keep, q
) -> torch.Tensor:
    """`_moved_values` for an `AgentBlockLinear` encoder first layer (zs: the critic's
    pre-activations on x). Moving agent i's action from u to a shifts only agent i's H1 encoder
    units, by the shared rows W_a - W_u; in the second layer's pre-activation
    z2 = b2 + sum_j relu(z1_j) @ W2_j (W2_j: agent j's [H1, H2] slice) only agent i's term
    changes, so the moved pre-activation is z2 + (relu(z1_i + W_a - W_u) - relu(z1_i)) @ W2_i:
    one H1 x H2 product per kept variant (rows grouped by agent), then the layers above.

    z1_i - W_u + W_a is one signed F.embedding_bag of three rows of a table of z1's and the
    action rows: the plain form, three index_select and two passes, gave the same bits and
    made the agents' targets 26% slower (5.7 against 4.5 ms; about 4% of an update) on the
    shipped skirmish/3m config's 32-episode batch (one process, both alternately, 100 calls
    each, load average 3.2 on 2 shared cores)."""
    e, m, n = actions.shape
    a = keep.shape[-1]
    enc, second = critic.layers[0], critic.layers[1]
    h1, h2 = enc.hidden, second.out_features
    z1, z2 = zs[0].reshape(e, m * n, h1), zs[1]  # row r*N + i: agent i's units; [E, M, H2]
    w_act = enc.block_weight[:, offset : offset + a]  # [E, A, H1]
    w2 = second.weight.view(e, n, h1, h2)
    out = q.view(e, m, 1, 1).expand(e, m, n, a).clone()
    todo = _todo(keep, actions)
    for k in range(e):
        agent, row, act = todo[k].permute(1, 0, 2).nonzero().unbind(1)  # agent-major
        if agent.numel() == 0:
            continue
        unit = row * n + agent  # agent i's units at that row: row `unit` of z1[k]
        taken = actions[k].reshape(-1).index_select(0, unit)
        table = torch.cat([z1[k], w_act[k]])  # z1's rows, then the action rows
        rows = torch.stack([unit, m * n + taken, m * n + act], 1)  # z1_i - W_u + W_a
        signs = table.new_tensor([1.0, -1.0, 1.0]).expand(rows.shape[0], 3)
        moved = F.embedding_bag(rows, table, mode="sum", per_sample_weights=signs).relu_()
        moved.sub_(table.index_select(0, unit).relu_())  # the change of relu(z1_i)
        z = z2[k].index_select(0, row)  # [R, H2], added to in place
        lo = 0
        for i, count in enumerate(torch.bincount(agent, minlength=n).tolist()):
            if count:
                z[lo : lo + count].addmm_(moved[lo : lo + count], w2[k, i])
                lo += count
        out[k, row, agent, act] = _above(critic, z, k, 2)
    return out
