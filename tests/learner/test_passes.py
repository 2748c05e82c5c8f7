"""Updates in passes (`learner.passes`, the `update_pass_rows` key of the value family and
RDN): the passes partition the batch, and a learner stepping in passes takes the update it
takes in one pass, to float32 rounding, for every value algorithm and both RDN recipes.

Tolerance: parameters after three updates agree to atol = 1e-5 * (1 + the largest |value|),
rtol 1e-4, and metrics to rel 1e-4 / abs 1e-6: the passes add the same gradients in another
order and cut trailing padding, nothing more. A learner that dropped a pass, counted an
episode twice or normalised a pass by its own size instead of the batch's would be off by
far more (each test checks the batch really went in several passes).
"""

from __future__ import annotations

import copy
import dataclasses

import pytest
import torch

from actors.envs.registry import make_vec_env
from cluster.bench.update import record_batch
from cluster.config.train import load_train_config
from learner import passes as passes_module
from learner.batch import TensorBatch
from learner.passes import episode_lengths, episode_passes, pass_plan
from learner.registry import get_algo

ENV = "skirmish/3m"


def _close(got: torch.Tensor, want: torch.Tensor) -> None:
    tol = 1e-5 * (1.0 + float(want.detach().abs().max()))
    torch.testing.assert_close(got, want, atol=tol, rtol=1e-4)


@pytest.fixture(scope="module")
def batch():
    """12 random-policy 3m episodes for each of 2 members (lengths 20-41 steps)."""
    return record_batch(ENV, 12, 2)


def test_passes_partition_the_batch(batch):
    """Every episode of every member is in exactly one pass, whole and unchanged; each pass
    is cut to its own longest episode and within the row budget (unless one episode alone
    exceeds it); a batch within the budget is one pass, itself."""
    tb = TensorBatch.from_episodes(batch)
    e, b, t, n = tb.shape
    lengths = episode_lengths(tb)
    assert int(lengths.min()) < int(lengths.max())  # the test needs unequal lengths
    assert list(episode_passes(tb, 0)) == [tb]
    assert list(episode_passes(tb, e * b * (t + 1) * n)) == [tb]
    budget = 4 * (t + 1) * n
    got = list(episode_passes(tb, budget))
    assert len(got) > 2
    seen = {m: [] for m in range(e)}
    for part in got:
        pe, pb, pt, pn = part.shape
        assert (pe, pn) == (e, n)
        assert pe * pb * (pt + 1) * pn <= budget or pb == 1
        part_lengths = episode_lengths(part)
        assert int(part_lengths.max()) == pt  # cut to its longest episode
        for m in range(e):
            for k in range(pb):
                # find the original episode by its content (episodes of a random policy differ)
                match = [
                    j
                    for j in range(b)
                    if int(lengths[m, j]) == int(part_lengths[m, k])
                    and torch.equal(tb.obs[m, j, : pt + 1], part.obs[m, k])
                    and torch.equal(tb.actions[m, j, :pt], part.actions[m, k])
                    and torch.equal(tb.reward[m, j, :pt], part.reward[m, k])
                    and torch.equal(tb.avail[m, j, : pt + 1], part.avail[m, k])
                    and torch.equal(tb.state[m, j, : pt + 1], part.state[m, k])
                    and torch.equal(tb.terminated[m, j, :pt], part.terminated[m, k])
                    and int(tb.policy_version[m, j]) == int(part.policy_version[m, k])
                ]
                assert len(match) == 1
                seen[m].append(match[0])
                # what the cut removed is padding only
                assert not tb.mask[m, match[0], pt:].any()
    for m in range(e):
        assert sorted(seen[m]) == list(range(b))


def test_pass_plan_keeps_the_budget_and_takes_at_least_one_episode():
    lengths = torch.tensor([[1, 2, 3, 10, 50], [1, 1, 4, 9, 60]])
    # rows of positions lo..hi-1: 2 members x episodes x (longest + 1) x 1 agent
    assert pass_plan(lengths, 1, 12) == [(0, 2), (2, 3), (3, 4), (4, 5)]
    assert pass_plan(lengths, 1, 0) == [(0, 5)]
    assert pass_plan(lengths, 1, 10**6) == [(0, 5)]
    assert pass_plan(lengths, 1, 1) == [(k, k + 1) for k in range(5)]


def _learner_pair(algo: str, overrides: list[str], rows: int):
    cfg = load_train_config(algo, ENV, [], overrides).algo
    assert cfg.update_pass_rows == passes_module.UPDATE_PASS_ROWS  # what ships is what we test
    one = dataclasses.replace(cfg, update_pass_rows=0)
    several = dataclasses.replace(cfg, update_pass_rows=rows)
    schema = make_vec_env(ENV, 1).info.schema()
    torch.manual_seed(0)
    first = get_algo(algo).build(one, schema, 2, "cpu")
    second = copy.deepcopy(first)
    second.cfg = several
    return first, second


def _check_same_updates(first, second, batch, modules: tuple[str, ...]) -> None:
    tb = TensorBatch.from_episodes(batch)
    rows = second.cfg.update_pass_rows
    assert len(episode_passes(tb, rows)) >= 3
    for k in range(3):
        got, want = second.step(batch), first.step(batch)
        assert got.keys() == want.keys()
        for name in got:
            assert got[name] == pytest.approx(want[name], rel=1e-4, abs=1e-6), (k, name)
        if k == 0:
            first.sync_targets(10**9)
            second.sync_targets(10**9)
    for name in modules:
        pairs = zip(
            getattr(first, name).parameters(), getattr(second, name).parameters(), strict=True
        )
        for p1, p2 in pairs:
            _close(p2, p1)


@pytest.mark.parametrize("algo", ["iql", "vdn", "qmix", "qmix_ns"])
def test_value_updates_in_passes_are_the_one_pass_updates(algo, batch):
    tb = TensorBatch.from_episodes(batch)
    rows = 4 * (tb.shape[2] + 1) * tb.shape[3]
    first, second = _learner_pair(algo, [], rows)
    modules = ("agent", "mixer") if algo.startswith("qmix") else ("agent",)
    _check_same_updates(first, second, batch, modules)


@pytest.mark.parametrize("recipe", ["shipped", "dissertation"])
def test_rdn_updates_in_passes_are_the_one_pass_updates(recipe, batch):
    """Shipped: counterfactual targets, one observation (packed real steps), TD(0.8);
    dissertation: taken-action targets, four observations (every step)."""
    tb = TensorBatch.from_episodes(batch)
    rows = 4 * (tb.shape[2] + 1) * tb.shape[3]
    first, second = _learner_pair("rdn", [f"recipe={recipe}"], rows)
    _check_same_updates(first, second, batch, ("critic", "agent"))


def test_a_negative_pass_budget_is_refused():
    for algo in ("vdn", "rdn"):
        with pytest.raises(ValueError, match="update_pass_rows must be >= 0"):
            load_train_config(algo, ENV, [], ["algo.update_pass_rows=-1"])
