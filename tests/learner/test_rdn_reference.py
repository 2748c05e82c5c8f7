"""The fast RDN (`RDNLearner.step`, `learner.rdn_fast.agent_targets`) against the dense
reference (`learner.rdn_reference`) on every shipped configuration: the same agent targets, the
same metrics and the same parameters after several updates, to float32 rounding.

Tolerance: values agree to atol = 1e-5 * (1 + the largest |value|) and rtol = 1e-4 (targets,
parameters), metrics to rel 1e-4 / abs 1e-6: the two sum the same products in different orders
(the structured first layer adds each observation's product separately; the reference multiplies
the dense input), nothing more.
"""

from __future__ import annotations

import copy
from importlib import resources

import pytest
import torch

from actors.envs.registry import make_vec_env
from cluster.bench.update import record_batch
from cluster.config.train import load_train_config
from learner.batch import TensorBatch
from learner.critic_inputs import AgentBlocks, obs_history
from learner.rdn import RDNLearner
from learner.rdn_fast import agent_targets
from learner.rdn_reference import (
    counterfactual_targets,
    critic_inputs,
    lrp_shares,
    obs_windows,
    reference_update,
)

ENVS = ("matrix/four_game", "skirmish/3m")  # smac/3m: the same config and sizes as skirmish/3m
RECIPES = ("shipped", "dissertation")  # `recipe=seed` is an alias of "dissertation"
SHIPPED = [(env, recipe) for env in ENVS for recipe in RECIPES]


def _close(got: torch.Tensor, want: torch.Tensor) -> None:
    tol = 1e-5 * (1.0 + float(want.detach().abs().max()))
    torch.testing.assert_close(got, want, atol=tol, rtol=1e-4)


def test_the_shipped_configurations_are_the_ones_tested_here():
    """Every env family and every RDN recipe that ships is covered by SHIPPED (a new layer
    makes this fail until it is added), and smac/3m runs skirmish/3m's config and sizes."""
    layers = resources.files("cluster.config") / "layers"
    families = {p.name.split(".")[0] for p in (layers / "envs").iterdir() if p.is_file()}
    assert families == {env.split("/")[0] for env in ENVS} | {"smac"}
    recipes = {p.name.split(".")[1] for p in (layers / "recipes").glob("rdn.*.yaml")}
    assert recipes | {"shipped"} == set(RECIPES)
    for recipe in RECIPES:
        smac = load_train_config("rdn", "smac/3m", [], [f"recipe={recipe}"]).algo
        assert smac == load_train_config("rdn", "skirmish/3m", [], [f"recipe={recipe}"]).algo


def _learners(env: str, recipe: str, e: int = 2) -> tuple[RDNLearner, RDNLearner]:
    cfg = load_train_config("rdn", env, [], [f"recipe={recipe}"]).algo
    schema = make_vec_env(env, 1).info.schema()
    torch.manual_seed(0)
    fast = RDNLearner(cfg, schema, n_ensemble=e)
    return fast, copy.deepcopy(fast)


@pytest.mark.parametrize(("env", "recipe"), SHIPPED)
def test_agent_targets_are_the_references(env, recipe):
    """`agent_targets` on the structured input: the reference's LRP shares and value, and
    (counterfactual targets) the reference's target of every kept (agent, action)."""
    learner, _ = _learners(env, recipe)
    cfg, n, a = learner.cfg, learner.info.n_agents, learner.info.n_actions
    tb = TensorBatch.from_episodes(record_batch(env, 6, 2))
    e, b, t, _ = tb.shape
    x = learner.critic_inputs(obs_history(tb.obs, cfg.obs_window)[:, :, :-1], tb.actions)
    assert isinstance(x, AgentBlocks)
    dense = critic_inputs(obs_windows(tb.obs, cfg.obs_window)[:, :, :-1], tb.actions, a)
    torch.testing.assert_close(x.dense(), dense, rtol=0, atol=0)
    keep = (tb.avail[:, :, :-1] & tb.mask.bool()[..., None, None]).view(e, b * t, n, a)
    offset = cfg.obs_window * learner.info.obs_dim
    counterfactual = cfg.agent_targets == "counterfactual"
    got = agent_targets(
        learner.critic,
        x,
        tb.actions.view(e, b * t, n),
        keep if counterfactual else None,
        cfg.lrp_eps,
        offset,
    )
    shares, q = lrp_shares(learner.critic, dense, n, cfg.lrp_eps)
    _close(got.shares, shares)
    _close(got.q, q)
    _close(got.shares.sum(-1), q)  # the shares add up to the critic's value
    if counterfactual:
        want = counterfactual_targets(learner.critic, dense, shares, q, offset, a)
        _close(got.every[keep], want[keep])
    else:
        assert got.every is None


@pytest.mark.parametrize(("env", "recipe"), SHIPPED)
def test_rdn_updates_are_the_references(env, recipe):
    """Two learners from the same initialisation (2 members), one stepping the fast way and
    one by `reference_update`, take three updates on the same recorded episodes (the target
    critic copied after the first): the same metrics and parameters."""
    fast, slow = _learners(env, recipe)
    batch = record_batch(env, 6, 2)
    for k in range(3):
        got, want = fast.step(batch), reference_update(slow, batch)
        assert got.keys() == want.keys()
        for name in got:
            assert got[name] == pytest.approx(want[name], rel=1e-4, abs=1e-6), (k, name)
        if k == 0:
            for learner in (fast, slow):
                learner.target_critic.copy_now()
    for net in ("critic", "agent"):
        pairs = zip(getattr(fast, net).parameters(), getattr(slow, net).parameters(), strict=True)
        for p1, p2 in pairs:
            _close(p1, p2)
