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

from learner.networks import MLP

LrpRule = Literal["eps_residual", "eps", "eps_nobias", "grad_x_input"]
LRP_RULES: tuple[str, ...] = ("eps_residual", "eps", "eps_nobias", "grad_x_input")


def _stabilise(z: torch.Tensor, eps: float) -> torch.Tensor:
    return z + eps * torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))


def lrp_epsilon(
    mlp: MLP, x: torch.Tensor, eps: float = 0.01, rule: LrpRule = "eps_residual"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Relevance of every input feature for the (single) output of `mlp`.

    Args:
        mlp: a ReLU MLP with one output unit.
        x: inputs, [E, M, D].
        eps: ε of the ε-rule (> 0).
        rule: bias handling; see the module docstring.
    Returns:
        (relevance [E, M, D], output [E, M]).
    """
    if rule == "grad_x_input":
        return _grad_x_input(mlp, x)
    with torch.no_grad():
        acts = mlp.activations(x)
        out = acts[-1]
        relevance = out
        for layer, a in zip(reversed(mlp.layers), reversed(acts[:-1]), strict=True):
            z = torch.bmm(a, layer.weight)
            if rule != "eps_nobias":
                z = z + layer.bias
            s = relevance / _stabilise(z, eps)
            relevance = a * torch.bmm(s, layer.weight.transpose(1, 2))
        out = out.squeeze(-1)
        if rule == "eps_residual":
            residual = out - relevance.sum(-1)
            weight = x.abs()
            total = weight.sum(-1, keepdim=True)
            share = torch.where(
                total > 0, weight / total.clamp_min(1e-12), torch.zeros_like(weight)
            )
            relevance = relevance + residual.unsqueeze(-1) * share
    return relevance, out


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
    return relevance.view(e, m, n_agents, d // n_agents).sum(-1)
