"""What the PG family trains on: the shipped configs, the data plan and the cycling table as
the local trainer uses them (LocalBuffer over the buffer service's own tables)."""

import numpy as np
import pytest

from buffer_service.episode import Episode
from buffer_service.local import LocalBuffer
from cluster.config.plan import data_plan
from cluster.config.train import load_train_config


def _episode(seq: int) -> Episode:
    t, n, o, a = 2, 2, 3, 2
    return Episode(
        obs=np.full((t + 1, n, o), seq, np.float32),
        state=np.zeros((t + 1, 4), np.float32),
        avail_actions=np.ones((t + 1, n, a), np.uint8),
        actions=np.zeros((t, n), np.int64),
        reward=np.zeros(t, np.float32),
        terminated=np.array([False, True]),
        filled=np.ones(t, bool),
        actor_id=0,
        episode_seq=seq,
        policy_version=seq,
    )


def _seqs(batch) -> list[int]:
    return sorted(int(x) for x in batch.obs[:, 0, 0, 0])


@pytest.mark.parametrize(
    "algo, num_envs, cycling, replay, extra_batch",
    [
        ("cac", 4, 4, None, 0),
        ("mcac", 4, 4, None, 0),
        ("coma", 4, 4, None, 0),
        ("ecac", 4, 32, 5000, 32),
        ("emcac", 4, 32, 5000, 32),
        ("qmix", 8, None, 5000, 0),  # value family: 8 envs, envs/skirmish.value.yaml
    ],
)
def test_shipped_layers_give_the_seeds_data_flow_on_skirmish(
    algo, num_envs, cycling, replay, extra_batch
):
    cfg = load_train_config(algo, "skirmish/3m")
    assert cfg.run.num_envs == num_envs
    assert cfg.run.test_interval == 10_000 and cfg.run.test_episodes == 20
    plan = data_plan(cfg)
    tables = {t.name: t for t in plan.tables}
    if cycling is not None:
        assert plan.table == "cycling" and plan.batch_size == cycling
        assert tables["cycling"].capacity == cycling
        assert tables["cycling"].max_times_sampled == cycling // num_envs
    if replay is not None:
        assert tables["replay"].capacity == replay
    assert plan.extra_batch_size == extra_batch
    # one learner step per round of new episodes for the PG family, one per episode (value)
    assert plan.updates_per_episode == (1.0 if cycling is None else 1 / num_envs)


def test_pg_configs_carry_the_seed_hyper_parameters():
    cfg = load_train_config("emcac", "skirmish/3m")
    a = cfg.algo
    assert (a.lr, a.critic_lr, a.gamma, a.td_lambda) == (5e-4, 5e-4, 0.99, 0.8)
    assert a.target_update_interval == 200 and a.critic_hidden == (64, 64)
    assert a.critic_input == "obs"
    assert load_train_config("coma", "skirmish/3m").algo.critic_hidden == (128, 128)


def test_cycling_table_trains_on_the_newest_32_and_drops_the_oldest():
    """E-CAC/EM-CAC: nothing until 32 episodes; then every step samples the whole table; each
    new round of 4 pushes the 4 oldest out; an episode is used at most 8 times."""
    plan = data_plan(load_train_config("emcac", "skirmish/3m"))
    buf = LocalBuffer(plan.tables, seed=0)
    seq = 0
    uses: dict[int, int] = {}
    for step in range(20):
        buf.insert([_episode(seq + k) for k in range(1, 5)])
        seq += 4
        ready = buf.ready(plan.table, plan.batch_size)
        assert ready == (seq >= 32)
        if not ready:
            continue
        got = _seqs(buf.sample(plan.table, plan.batch_size))
        assert got == list(range(seq - 31, seq + 1)), f"step {step}"
        for s in got:
            uses[s] = uses.get(s, 0) + 1
    assert max(uses.values()) == 8
    assert buf.stats()["tables"]["cycling"]["size"] <= 32


def test_on_policy_variants_use_each_fresh_episode_once():
    plan = data_plan(load_train_config("cac", "skirmish/3m"))
    buf = LocalBuffer(plan.tables, seed=0)
    for r in range(3):
        new = list(range(4 * r + 1, 4 * r + 5))
        buf.insert([_episode(s) for s in new])
        assert buf.ready(plan.table, plan.batch_size)
        assert _seqs(buf.sample(plan.table, plan.batch_size)) == new
        assert not buf.ready(plan.table, plan.batch_size)  # used once, then gone
